"""A map as an MCAP recording for offline viewing: its grid, and the scans of its batch log.

What ``ros2 bag record -s mcap`` would have written had the robot's scans and map_server's map
been recorded (ROS 2 profile, ``cdr`` messages, ``ros2msg`` schemas with their dependencies,
zstd chunks), so that Foxglove, ``ros2 bag play`` and rosbags read it without our typestore:

==========  ==============================  =====================================================
topic       type                            holds
==========  ==============================  =====================================================
``/map``    ``nav_msgs/msg/OccupancyGrid``  the grid at the recording's version: the bytes of
                                            ``GET /maps/{name}/occupancy_grid.cdr`` (trinary,
                                            Nav2's thresholds), latched as map_server's; logged
                                            at the first scan's time, so a viewer shows the map
                                            under the scans from the start
``/scan``   ``sensor_msgs/msg/LaserScan``   each LaserScan as posted (REP 117 ranges: +inf no
                                            return, NaN and -inf kept), in the frame
                                            ``<frame_id>_laser``
``/tf``     ``tf2_msgs/msg/TFMessage``      beside each LaserScan, at its stamp: the map's frame
                                            to ``<frame_id>_laser``, the pose it was posted with
``/points`` ``sensor_msgs/msg/PointCloud2`` each point cloud (2-D or 3-D) as ``x, y, z`` float32 in
                                            the map's frame (stored there; z = 0 on 2-D maps)
==========  ==============================  =====================================================

Which scans: those of the batches after the map's latest snapshot, up to the grid's version (what a
restart replays; older scans stay in the map's history but are not exported; ``since_version`` says
where the log starts). An imported map's first batch (a saved map's cells) holds no scan: the grid shows it. At most ``FUZZYRISK_SNAPSHOT_EVERY`` batches, and ``FUZZYRISK_SNAPSHOT_LOG_BYTES``
of them (plus one).

Stamps: derived, not the scans' stored stamps (``GET /maps/{name}/trajectory`` gives those). Of the N scans, in version order and in order within each
batch, scan k (1..N) is stamped ``updated - (N - k) * 0.1 s``: the last at ``updated``, the time
the map reached this version (its last batch's commit; the grid's stamp), one every 0.1 s before
it (10 Hz, a common laser's rate). A function of the version and the log, so every read of one
version (with one snapshot) is the same bytes.

Nothing here knows HTTP beyond its error classes: ``app.api.routes.recordings`` serves the file.
"""

from __future__ import annotations

import io
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from app.maps import logcodec
from app.scans import Scan
from app.formats import etags
from app.formats import exports
from app.ros import messages_out
from app.errors import TooLarge, Unavailable
from app.formats.exports import NAV2_FREE_THRESH, NAV2_OCCUPIED_THRESH
from app.ros import msgtypes
from app.ros.msgtypes import typestore
from app.maps import GridSnapshot
from app.schemas import WHOLE_MAP, GridWindow
from app.storage import StoredMap
from fuzzyocc import LaserScan

LASER_SCAN = "sensor_msgs/msg/LaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
SCAN_TOPIC = "/scan"
CLOUD_TOPIC = "/points"
TF_TOPIC = "/tf"
#: The time between two consecutive scans' stamps (10 Hz).
SCAN_PERIOD_NS = 100_000_000
#: The response header naming the snapshot version the recorded scans start after.
SINCE_HEADER = "X-Scans-Since-Version"
#: ``sensor_msgs/PointField.FLOAT32``.
_FLOAT32 = 7
#: Bytes of a message besides its arrays and frame names, at most (encapsulation, stamp, scalars, lengths).
_MESSAGE_OVERHEAD = 128


def sensor_frame(frame_id: str) -> str:
    """The frame of a map's LaserScans in a recording: ``<frame_id>_laser`` (never the map's own frame)."""
    return f"{frame_id}_laser"


def scan_stamps_ns(last_ns: int, count: int) -> list[int]:
    """Stamps of ``count`` scans in recorded order, ``SCAN_PERIOD_NS`` apart, the last at ``last_ns``."""
    return [last_ns - (count - 1 - k) * SCAN_PERIOD_NS for k in range(count)]


# ---------------------------------------------------------------- messages


def _header(frame_id: str, stamp_ns: int) -> Any:
    types = typestore().types
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](**msgtypes.ros_time_of_ns(stamp_ns)), frame_id=frame_id)


def laser_scan_message(scan: LaserScan, *, frame_id: str, stamp_ns: int) -> Any:
    """A rosbags ``sensor_msgs/msg/LaserScan`` of a stored scan: its angles, limits and ranges (float32)."""
    with np.errstate(over="ignore"):  # a range beyond float32 is +inf there, as a driver would send it
        ranges = np.asarray(scan.ranges, dtype=np.float32)
    return typestore().types[LASER_SCAN](
        header=_header(frame_id, stamp_ns), angle_min=scan.angle_min,
        angle_max=scan.angle_min + (ranges.size - 1) * scan.angle_increment, angle_increment=scan.angle_increment,
        time_increment=0.0, scan_time=SCAN_PERIOD_NS / msgtypes.NS_PER_S, range_min=scan.range_min,
        range_max=scan.range_max, ranges=ranges, intensities=np.zeros(0, dtype=np.float32),
    )


def sensor_transform_message(pose: Sequence[float], *, frame_id: str, child_frame_id: str, stamp_ns: int) -> Any:
    """A ``tf2_msgs/msg/TFMessage`` placing ``child_frame_id`` at the planar ``pose`` (x, y, yaw) in ``frame_id``."""
    types = typestore().types
    x, y, yaw = pose
    transform = types["geometry_msgs/msg/Transform"](
        translation=types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=0.0),
        rotation=types["geometry_msgs/msg/Quaternion"](**messages_out.yaw_quaternion(float(yaw))),
    )
    stamped = types["geometry_msgs/msg/TransformStamped"](
        header=_header(frame_id, stamp_ns), child_frame_id=child_frame_id, transform=transform)
    return types[TF_MESSAGE](transforms=[stamped])


def point_cloud2_message(points: np.ndarray, *, frame_id: str, stamp_ns: int) -> Any:
    """A dense, unorganised ``sensor_msgs/msg/PointCloud2`` of (N, 2) or (N, 3) points: ``x, y, z`` float32."""
    types = typestore().types
    xyz = np.zeros((points.shape[0], 3), dtype="<f4")
    xyz[:, :points.shape[1]] = points
    fields = [types["sensor_msgs/msg/PointField"](name=axis, offset=4 * i, datatype=_FLOAT32, count=1)
              for i, axis in enumerate("xyz")]
    return types[POINT_CLOUD2](
        header=_header(frame_id, stamp_ns), height=1, width=xyz.shape[0], fields=fields, is_bigendian=False,
        point_step=12, row_step=12 * xyz.shape[0], data=np.frombuffer(xyz.tobytes(), dtype=np.uint8),
        is_dense=True,
    )


def grid_cdr(grid: GridSnapshot) -> bytes:
    """The map's OccupancyGrid as ``GET /maps/{name}/occupancy_grid.cdr`` answers it with no query."""
    risk, observed = grid.planar(None, None)
    data = exports.occupancy_data(risk, observed, mode="trinary", free_thresh=NAV2_FREE_THRESH,
                                  occupied_thresh=NAV2_OCCUPIED_THRESH)
    message = messages_out.occupancy_grid_message(
        data, width=risk.shape[0], height=risk.shape[1], resolution=grid.spec.resolution,
        origin_xy=grid.spec.origin[:2], frame_id=grid.frame_id, stamp=msgtypes.ros_time_of_iso(grid.updated),
    )
    return messages_out.occupancy_grid_cdr(message)


# ---------------------------------------------------------------- the file


def _scans(log: Sequence[tuple[int, bytes]]) -> Iterator[Scan]:
    """The scans of the log in recorded order, one batch decoded at a time (a prior or an edit has none: the grid
    holds what they did)."""
    for version, payload in log:
        try:
            batch = logcodec.decode(payload)
        except logcodec.CorruptBatch as exc:
            raise Unavailable(f"the map's stored batch {version} is corrupt ({exc}): it cannot be exported") from None
        if isinstance(batch, list):
            yield from batch


def mcap_file(grid: GridSnapshot, log: Sequence[tuple[int, bytes]], *, since_version: int, max_bytes: int) -> bytes:
    """The recording of ``grid`` and the batches of ``log`` (version, payload), in order (module doc).

    ``TooLarge`` before anything is serialized when the messages would take more than ``max_bytes``
    (the grid's CDR and each scan's arrays, plus a bound on each message's header).
    """
    grid_bytes = grid_cdr(grid)
    laser_frame = sensor_frame(grid.frame_id)
    overhead = _MESSAGE_OVERHEAD + len(grid.frame_id) + len(laser_frame)
    # first pass: count and size the messages (decoding is a copy; serializing and compressing are the work)
    lasers = clouds = 0
    size = len(grid_bytes)
    for scan in _scans(log):
        if isinstance(scan, LaserScan):
            lasers += 1
            size += 4 * scan.ranges.size + 2 * overhead  # the scan and its transform
        else:
            clouds += 1
            size += 12 * scan.points.shape[0] + overhead
    if size > max_bytes:
        raise TooLarge(
            f"the map's log since version {since_version} holds {lasers} LaserScans and {clouds} point clouds: "
            f"with the grid, about {size:,} bytes of messages, more than FUZZYRISK_MAX_RECORDING_BYTES "
            f"({max_bytes:,}); raise it, or export after the map's next snapshot (FUZZYRISK_SNAPSHOT_EVERY)"
        )
    stamps = scan_stamps_ns(msgtypes.ns_of_ros_time(msgtypes.ros_time_of_iso(grid.updated)), lasers + clouds)

    out = io.BytesIO()
    writer = Writer(out, compression=CompressionType.ZSTD)
    writer.start(profile="ros2", library="fuzzyrisk")
    # channels in a fixed order, only those with messages: one log gives one file
    channel = {messages_out.MAP_TOPIC: messages_out.ros2_channel(writer, msgtype=messages_out.OCCUPANCY_GRID, topic=messages_out.MAP_TOPIC,
                                                     qos_profiles=messages_out.MAP_QOS_PROFILES)}
    if lasers:
        channel[TF_TOPIC] = messages_out.ros2_channel(writer, msgtype=TF_MESSAGE, topic=TF_TOPIC)
        channel[SCAN_TOPIC] = messages_out.ros2_channel(writer, msgtype=LASER_SCAN, topic=SCAN_TOPIC)
    if clouds:
        channel[CLOUD_TOPIC] = messages_out.ros2_channel(writer, msgtype=POINT_CLOUD2, topic=CLOUD_TOPIC)
    sequence = dict.fromkeys(channel, 0)

    def add(topic: str, message: Any, msgtype: str, stamp_ns: int) -> None:
        data = bytes(typestore().serialize_cdr(message, msgtype))
        writer.add_message(channel[topic], log_time=stamp_ns, data=data, publish_time=stamp_ns,
                           sequence=sequence[topic])
        sequence[topic] += 1

    first_ns = stamps[0] if stamps else msgtypes.ns_of_ros_time(msgtypes.ros_time_of_iso(grid.updated))
    writer.add_message(channel[messages_out.MAP_TOPIC], log_time=first_ns, data=grid_bytes, publish_time=first_ns,
                       sequence=0)
    for scan, stamp_ns in zip(_scans(log), stamps, strict=True):
        if isinstance(scan, LaserScan):
            # the transform first: a player publishes it before the scan that needs it
            add(TF_TOPIC, sensor_transform_message(scan.pose, frame_id=grid.frame_id, child_frame_id=laser_frame,
                                                   stamp_ns=stamp_ns), TF_MESSAGE, stamp_ns)
            add(SCAN_TOPIC, laser_scan_message(scan, frame_id=laser_frame, stamp_ns=stamp_ns), LASER_SCAN, stamp_ns)
        else:
            add(CLOUD_TOPIC, point_cloud2_message(scan.points, frame_id=grid.frame_id, stamp_ns=stamp_ns),
                POINT_CLOUD2, stamp_ns)
    writer.finish()
    return out.getvalue()


@dataclass(frozen=True)
class Recording:
    """One export: what tells it apart (the ETag's variant), and its bytes unless the client holds them."""

    grid: GridSnapshot
    variant: dict[str, object]
    etag: str
    #: the snapshot version the scans start after (the batches ``since_version + 1`` .. ``grid.version``)
    since_version: int
    #: None: ``If-None-Match`` named ``etag`` (304, nothing built)
    data: bytes | None


def export(grid: GridSnapshot, stored: StoredMap, *, media_type: str, max_bytes: int,
           if_none_match: str | None, window: GridWindow = WHOLE_MAP) -> Recording:
    """The recording of a map's grid (cut to ``window``, as ``MapReads.render_log`` read it) and stored log
    (``MapReads.render_log`` runs it in a read thread).

    The ETag covers the snapshot version: a snapshot taken at the map's version empties the log,
    and with it the file changes while the version does not.
    """
    variant: dict[str, object] = {"read": "export/mcap", "since_version": stored.snapshot_version,
                                  "media_type": media_type, **window.variant()}
    etag = grid.etag(variant)
    if etags.matches(if_none_match, etag):
        return Recording(grid, variant, etag, stored.snapshot_version, None)
    data = mcap_file(grid, logcodec.moved(stored.batches, stored.poses), since_version=stored.snapshot_version,
                     max_bytes=max_bytes)
    return Recording(grid, variant, etag, stored.snapshot_version, data)
