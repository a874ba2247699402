"""A map as a recording for offline viewing: an MCAP file of its grid and the scans of its batch log."""

from __future__ import annotations

import functools

from fastapi import APIRouter, Response

from app.formats import etags
from app.reads import recording
from app.ros import messages_out
from app.api.deps import MapNamePath, ServiceDep
from app.api.largebody import bytes_response
from app.formats.mediatypes import MCAP
from app.api.routes.risk import (
    _NOT_FOUND,
    Accept,
    IfNoneMatch,
    WindowQuery,
    _binary_200,
    _grid_headers,
    _media_type,
)

router = APIRouter(prefix="/maps", tags=["recordings"])

_MCAP_200 = _binary_200(
    MCAP, f"an MCAP file (ROS 2 profile: cdr messages, ros2msg schemas): the grid on {messages_out.MAP_TOPIC}, the "
    f"LaserScans on {recording.SCAN_TOPIC} with their {recording.TF_TOPIC}, the point clouds on "
    f"{recording.CLOUD_TOPIC}",
)
_HEADERS = {**_MCAP_200[200]["headers"], recording.SINCE_HEADER: {
    "description": "the map version the recorded scans start after: those of the batches since the map's latest "
    "snapshot are recorded (older ones stay in the map's history, not in the recording)", "schema": {"type": "integer"}}}
_MCAP_200[200]["headers"] = _HEADERS
_RESPONSES = {
    **_NOT_FOUND,
    304: {"description": "If-None-Match names the current ETag: the file would be the same bytes (no body)",
          "headers": _HEADERS},
    **_MCAP_200,
    413: {"description": "the messages would take more than FUZZYRISK_MAX_RECORDING_BYTES"},
}


@router.get("/{name}/export/mcap", response_class=Response, responses=_RESPONSES)
async def export_mcap(name: MapNamePath, service: ServiceDep, window: WindowQuery,
                      if_none_match: IfNoneMatch = None, accept: Accept = None) -> Response:
    """The map as an MCAP file for Foxglove, ``ros2 bag play`` or rosbags: its grid and its recent scans.

    ``/map``: the ``nav_msgs/msg/OccupancyGrid`` of ``occupancy_grid.cdr`` (latched), logged at
    the first scan's time. ``/scan``: each LaserScan as posted (REP 117 ranges) in the frame
    ``<frame_id>_laser``, with a ``/tf`` from the map's frame to it at the same stamp (the posted
    pose). ``/points``: each point cloud as a ``sensor_msgs/msg/PointCloud2`` (x, y, z float32) in
    the map's frame. Only the batches since the map's latest snapshot are stored, so only their
    scans are recorded (``X-Scans-Since-Version``; a snapshot every ``FUZZYRISK_SNAPSHOT_EVERY``
    batches). Batches keep no robot time: the last scan is stamped with the map's ``updated``
    time, each earlier one 0.1 s before the next, so every read of one version (and snapshot) is
    the same file. 413 beyond ``FUZZYRISK_MAX_RECORDING_BYTES``. A window (``min``, ``max``) cuts
    the grid on ``/map`` to its cells; the scans are recorded whole.
    """
    made = await service.reads.render_log(name, functools.partial(
        recording.export, media_type=_media_type(accept, MCAP), max_bytes=service.settings.max_recording_bytes,
        if_none_match=if_none_match, window=window,
    ), window)
    since = {recording.SINCE_HEADER: str(made.since_version)}
    if made.data is None:
        unchanged = etags.not_modified(made.etag, made.grid.version)
        unchanged.headers.update(since)
        return unchanged
    headers = {**_grid_headers(name, made.grid, made.variant), **since,
               "Content-Disposition": f'attachment; filename="{name}-v{made.grid.version}.mcap"'}
    return bytes_response(made.data, media_type=str(made.variant["media_type"]), headers=headers)
