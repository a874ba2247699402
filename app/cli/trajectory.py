"""A corrected trajectory put on a map of the service, and its rebuild waited for (re-fusion after a loop closure).

The path is a ``nav_msgs/Path`` of sensor poses in the map's frame (``messages_out.pose_stamped``, the shape
``GET /maps/{name}/trajectory`` answers), sent by ``PUT /maps/{name}/trajectory``. The service answers 202 with the
correction's ``RebuildStatus`` once the correction is durable, and rebuilds the map in the background;
:func:`wait_for_rebuild` polls ``GET /maps/{name}/rebuild`` until that correction's rebuild is done, showing the scans
re-fused of the total on a :class:`~app.cli.progress.Progress`. ``python -m app.import_log --trajectory`` is its
command.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from typing import Any
from urllib.parse import quote

from app.cli.common import ImportFailed, ServiceClient
from app.cli.progress import Progress
from app.ros.messages_out import pose_stamped

#: Seconds between two reads of a rebuild's progress.
POLL_S = 0.5


def sensor_path(poses: Sequence[tuple[float, float, float]], stamps_ns: Sequence[int], frame_id: str
                ) -> dict[str, Any]:
    """The ``nav_msgs/Path`` of 2-D sensor poses ``(x, y, theta)`` taken at ``stamps_ns`` (Unix nanoseconds), in the
    map's frame ``frame_id``: each theta as ``yaw_quaternion`` writes it, so a map's own poses go back bit for bit."""
    return {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": frame_id},
            "poses": [pose_stamped((x, y), theta, stamp_ns=stamp, frame_id=frame_id)
                      for (x, y, theta), stamp in zip(poses, stamps_ns, strict=True)]}


def map_frame(client: ServiceClient, name: str) -> str:
    """The ROS frame of the service's map ``name`` (a corrected trajectory must be in it)."""
    _, data = client.call("GET", f"/maps/{quote(name, safe='')}")
    return str(json.loads(data)["frame_id"])


def put_trajectory(client: ServiceClient, name: str, path: dict[str, Any]) -> dict[str, Any]:
    """``PUT /maps/{name}/trajectory``: the correction's ``RebuildStatus`` once the service holds it durably."""
    _, data = client.call("PUT", f"/maps/{quote(name, safe='')}/trajectory", json.dumps(path).encode(), ok=(202,))
    return dict(json.loads(data)["rebuild"])


def wait_for_rebuild(client: ServiceClient, name: str, correction: str, progress: Progress, *,
                     poll_s: float = POLL_S) -> dict[str, Any]:
    """Poll the map's rebuild until the one of ``correction`` (its id) is done: its final ``RebuildStatus``.

    Its scans re-fused go to ``progress`` (stage ``rebuilding``). ``ImportFailed`` when the rebuild failed (the
    service's reason), or when the map's rebuild is no longer this correction's (another PUT superseded it).
    """
    where = f"/maps/{quote(name, safe='')}/rebuild"
    total = None
    while True:
        status = json.loads(client.call("GET", where)[1])
        if status["id"] != correction:
            raise ImportFailed(f"the correction {correction} of {name!r} was superseded by "
                               f"{status['id'] or 'none'} before its rebuild finished (GET {client.url}{where})")
        if status["scans_total"] and status["scans_total"] != total:
            total = status["scans_total"]
            progress.stage("rebuilding", total, "scans")
        if total:
            progress.update(status["scans_done"])
        if status["state"] == "failed":
            raise ImportFailed(f"the rebuild of {name!r} failed: {status['error']}")
        if status["state"] == "done":
            progress.close()
            return dict(status)
        time.sleep(poll_s)
