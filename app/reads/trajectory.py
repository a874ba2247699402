"""A map's trajectory: the sensor pose of each stored scan, with its stamp, as ``Trajectory`` JSON (a ``nav_msgs/Path``).

Read from the batch log's records without decoding the beams (``logcodec.scan_poses``). A LaserScan's pose is
``(x, y, theta)``, given as z 0 and a yaw quaternion (``messages_out.yaw_quaternion``, as a plan's poses), as is a
2-D cloud's; a 3-D cloud's is its sensor pose, its quaternion as posted; a cloud stored in the map frame (before
clouds were stored as taken) keeps only its sensor origin, with the identity orientation. A scan stored before scans kept stamps is stamped 0 (ROS's "no time") and counted in
``unstamped``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence

from app.errors import TooLarge, Unavailable
from app.maps import logcodec
from app.ros.messages_out import pose_stamped
from app.schemas import Trajectory


def scan_poses(log: Sequence[tuple[int, bytes]], max_poses: int,
               moved: Mapping[int, bytes] | None = None) -> list[logcodec.ScanPose]:
    """The poses of the log's scans, in version order and in order within a batch, where ``moved`` (``StoredMap.poses``)
    put them; ``TooLarge`` past ``max_poses`` (``FUZZYRISK_MAX_TRAJECTORY_POSES``), as soon as the count passes it."""
    poses: list[logcodec.ScanPose] = []
    for version, payload in log:
        try:
            poses += logcodec.scan_poses(payload, None if moved is None else moved.get(version))
        except logcodec.CorruptBatch as exc:
            raise Unavailable(f"the map's stored batch {version} is corrupt ({exc}): its trajectory cannot be "
                              "read") from None
        if len(poses) > max_poses:
            raise TooLarge(f"the map's trajectory has more than {max_poses:,} poses, more than "
                           "FUZZYRISK_MAX_TRAJECTORY_POSES: raise it to read them")
    return poses


#: Poses serialised at a time: one ``json.dumps`` holds the GIL for its whole call, and every other request with it.
_CHUNK = 4096
_NO_POSES = b'"poses":[]'


def trajectory_json(log: Sequence[tuple[int, bytes]], *, moved: Mapping[int, bytes], frame_id: str,
                    stamp: dict[str, int], version: int, from_version: int, max_poses: int) -> bytes:
    """``Trajectory`` of the batches of ``log`` (version, payload), at the poses ``moved`` gave them, as JSON bytes (module
    doc).

    The small fields go through the model; the poses, built in its shape by ``messages_out.pose_stamped``, are
    written by ``json`` a chunk at a time (what the model reads back, every number as stored: tested): validating
    100,000 of them through the model took 4 s, the rest of the answer 2.
    """
    poses = scan_poses(log, max_poses, moved)
    head = Trajectory.model_validate({
        "header": {"stamp": stamp, "frame_id": frame_id},
        "poses": [],
        "version": version,
        "from_version": from_version,
        "unstamped": sum(pose.stamp_ns is None for pose in poses),
    }).model_dump_json().encode()
    assert head.count(_NO_POSES) == 1
    chunks = (json.dumps([pose_stamped(pose.position, pose.yaw, stamp_ns=pose.stamp_ns or 0, frame_id=frame_id,
                                    orientation=pose.orientation)
                       for pose in poses[i:i + _CHUNK]], separators=(",", ":"))
              for i in range(0, len(poses), _CHUNK))
    return head.replace(_NO_POSES, b'"poses":[' + ",".join(chunk[1:-1] for chunk in chunks).encode() + b"]")
