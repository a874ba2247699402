"""ROS 2 messages out of the service: ``nav_msgs/Path`` for plans, ``nav_msgs/OccupancyGrid`` as CDR and MCAP.

Messages are data here, as in rosbags (a typestore built from the message definitions, no
ROS install): the CDR bytes are those ``rclpy.serialization.serialize_message`` writes for
the same message (little-endian CDR after its 4-byte encapsulation header), and the MCAP file
is what ``ros2 bag record -s mcap`` writes for one message on ``/map``. Nothing here knows
about maps or HTTP: frames, stamps and arrays come in as arguments.

Stamps are ROS time without simulation time: Unix time as ``{"sec", "nanosec"}`` (``app.ros.msgtypes``, with
the typestore).
"""

from __future__ import annotations

import dataclasses
import io
import struct
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from app.ros.msgtypes import ros_time_of_ns, typestore
from fuzzyocc import tf

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
#: The content type of a CDR-serialized OccupancyGrid (``format=cdr``): a vendor type naming the message.
CDR_MEDIA_TYPE = "application/vnd.ros2.nav_msgs.msg.OccupancyGrid+cdr"
#: The topic of the OccupancyGrid in the MCAP file: map_server's.
MAP_TOPIC = "/map"
#: map_server's QoS for /map (reliable, transient local, keep last 1), as rosbag2 writes it in a channel's
#: ``offered_qos_profiles``: ``ros2 bag play`` republishes the map latched, as map_server does. Durations
#: are rmw's "unspecified" (sec 9223372036, nsec 854775807: infinite).
_INFINITE = "{sec: 9223372036, nsec: 854775807}"
MAP_QOS_PROFILES = (
    "- history: keep_last\n  depth: 1\n  reliability: reliable\n  durability: transient_local\n"
    f"  deadline: {_INFINITE}\n  lifespan: {_INFINITE}\n  liveliness: automatic\n"
    f"  liveliness_lease_duration: {_INFINITE}\n  avoid_ros_namespace_conventions: false"
)
#: rclcpp's default QoS (reliable, volatile, keep last 10), as rosbag2 records it: what a player offers for the
#: other topics (a reliable offer serves both reliable and best-effort subscribers).
DEFAULT_QOS_PROFILES = (
    "- history: keep_last\n  depth: 10\n  reliability: reliable\n  durability: volatile\n"
    f"  deadline: {_INFINITE}\n  lifespan: {_INFINITE}\n  liveliness: automatic\n"
    f"  liveliness_lease_duration: {_INFINITE}\n  avoid_ros_namespace_conventions: false"
)
#: The state spaces whose path points carry the planned yaw as a third value.
YAW_SPACES = frozenset({"SE2", "Dubins", "ReedsShepp"})
#: Shorter horizontal steps than this have no heading of their own (repeated points, a vertical R3 step).
_MIN_STEP_M = 1e-9


# ---------------------------------------------------------------- time (ROS time itself: app.ros.msgtypes)


def zip_date_time(text: str) -> tuple[int, int, int, int, int, int]:
    """A zip entry's date and time (UTC, whole seconds) of an ISO 8601 time: files of one map version match."""
    return datetime.fromisoformat(text).astimezone(UTC).timetuple()[:6]


# ---------------------------------------------------------------- nav_msgs/Path


def yaw_quaternion(yaw: float) -> dict[str, float]:
    """``geometry_msgs/Quaternion`` of a rotation by ``yaw`` about +z (REP 103: counter-clockwise from +x)."""
    return dict(zip("xyzw", tf.yaw_quaternion(yaw), strict=True))


#: The orientation of a cloud stored in the map frame (before clouds were stored as taken): its sensor's origin only.
_IDENTITY = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def pose_stamped(position: Sequence[float], yaw: float | None, *, stamp_ns: int, frame_id: str,
                 orientation: Sequence[float] | None = None) -> dict[str, Any]:
    """``geometry_msgs/PoseStamped`` as JSON of a sensor pose taken at ``stamp_ns``: ``position`` x, y(, z; 0 when
    left out) and ``yaw`` as a quaternion, or ``orientation`` ``(qx, qy, qz, qw)`` as given (neither: the identity).
    A trajectory's pose, out and in."""
    x, y, *rest = position
    if orientation is not None:
        quaternion = dict(zip(("x", "y", "z", "w"), (float(v) for v in orientation), strict=True))
    else:
        quaternion = _IDENTITY if yaw is None else yaw_quaternion(yaw)
    return {"header": {"stamp": ros_time_of_ns(stamp_ns), "frame_id": frame_id},
            "pose": {"position": {"x": x, "y": y, "z": rest[0] if rest else 0.0}, "orientation": quaternion}}


def path_yaws(path: np.ndarray, state_space: str, goal_yaw: float | None = None) -> np.ndarray:
    """The yaw of each pose of a planned path, radians.

    SE2, Dubins, ReedsShepp: the planned yaw (the third value; a Reeds-Shepp car reversing keeps
    its heading). R2 and R3: the heading of the horizontal step to the next point that moves
    (a flying robot's yaw follows the path over the ground, it does not pitch to climb); the last
    pose keeps the heading of the step before it, or takes ``goal_yaw`` when given (as Nav2's
    planners give the last pose the goal's orientation); poses after the last horizontal step keep
    its heading; a path with no horizontal step at all has ``goal_yaw`` or 0 everywhere.

    Parameters
    ----------
    path : (n, 2) or (n, 3) float
        The plan's points: [x, y], [x, y, yaw] or [x, y, z].
    """
    n = len(path)
    if n and state_space in YAW_SPACES:
        return np.asarray(path[:, 2], dtype=np.float64)
    default = 0.0 if goal_yaw is None else float(goal_yaw)
    yaws = np.full(n, default)
    if n < 2:
        return yaws
    steps = np.diff(path[:, :2], axis=0)
    moves = np.hypot(steps[:, 0], steps[:, 1]) > _MIN_STEP_M
    headings = np.arctan2(steps[:, 1], steps[:, 0])
    following = None  # heading of the next step that moves, walking back from the end
    for k in range(n - 2, -1, -1):
        if moves[k]:
            following = headings[k]
        if following is not None:
            yaws[k] = following
    last_moving = np.flatnonzero(moves)
    if last_moving.size:
        tail = headings[last_moving[-1]]
        yaws[last_moving[-1] + 1:] = tail  # no step that moves after these: keep the last heading
        if goal_yaw is not None:
            yaws[-1] = goal_yaw
    return yaws


def path_message(
    path: Sequence[Sequence[float]], *, state_space: str, frame_id: str, stamp: dict[str, int],
    goal_yaw: float | None = None,
) -> dict[str, Any]:
    """``nav_msgs/Path`` as JSON (rosbridge's and Foxglove's shape): ``{"header", "poses"}``.

    Each pose is a ``geometry_msgs/PoseStamped`` with the path's header, as Nav2's planners write
    them; ``z`` is 0 on 2-D maps; orientations from ``path_yaws``.
    """
    header = {"stamp": dict(stamp), "frame_id": frame_id}
    # no path (status none): no poses, in the state space's width (R3's z is read below)
    empty = np.zeros((0, 3 if state_space == "R3" else 2))
    points = np.asarray(path, dtype=np.float64).reshape(len(path), -1) if len(path) else empty
    yaws = path_yaws(points, state_space, goal_yaw)
    z = points[:, 2] if state_space == "R3" else np.zeros(len(points))
    poses = [
        {"header": header,
         "pose": {"position": {"x": float(p[0]), "y": float(p[1]), "z": float(height)},
                  "orientation": yaw_quaternion(float(yaw))}}
        for p, height, yaw in zip(points, z, yaws, strict=True)
    ]
    return {"header": header, "poses": poses}


# ---------------------------------------------------------------- nav_msgs/OccupancyGrid


def occupancy_grid_message(
    data: np.ndarray, *, width: int, height: int, resolution: float, origin_xy: Sequence[float], frame_id: str,
    stamp: dict[str, int],
) -> Any:
    """A rosbags ``nav_msgs/msg/OccupancyGrid`` (``data`` int8, ``data[j * width + i]``); load time = ``stamp``."""
    types = typestore().types
    time_type = types["builtin_interfaces/msg/Time"]
    return types[OCCUPANCY_GRID](
        header=types["std_msgs/msg/Header"](stamp=time_type(**stamp), frame_id=frame_id),
        info=types["nav_msgs/msg/MapMetaData"](
            map_load_time=time_type(**stamp), resolution=float(resolution), width=int(width), height=int(height),
            origin=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=float(origin_xy[0]), y=float(origin_xy[1]), z=0.0),
                orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        ),
        data=np.ascontiguousarray(data, dtype=np.int8),
    )


def occupancy_grid_cdr(message: Any) -> bytes:
    """The message as CDR bytes (what ``rclpy.serialization.serialize_message`` writes); see ``occupancy_grid_cdr_parts``."""
    return b"".join(occupancy_grid_cdr_parts(message))


def occupancy_grid_cdr_parts(message: Any) -> tuple[bytes, memoryview]:
    """The message's CDR bytes in two pieces, the second the cells themselves (no copy of them).

    The fields before ``data`` are serialized by rosbags with an empty ``data``, whose length is
    the message's last 4 bytes; the cells follow that length, int8 needing no alignment. Each
    copy of 16 M cells held the GIL while every other request waited (rosbags
    zero-fills a buffer and copies them in, about 19 ms; joining the pieces into one bytes
    object, a few ms more): the service sends the pieces as they are. Joined, equal to
    rosbags' serialization of the whole message (tested).
    """
    data = np.ascontiguousarray(message.data, dtype=np.int8)
    head = typestore().serialize_cdr(dataclasses.replace(message, data=data[:0]), OCCUPANCY_GRID)
    return bytes(head[:-4]) + struct.pack("<I", data.size), memoryview(data).cast("B")


def occupancy_grid_mcap(cdr: bytes, *, log_time_ns: int, topic: str = MAP_TOPIC) -> bytes:
    """An MCAP file (ROS 2 profile, zstd chunks) holding one OccupancyGrid on ``topic``, logged at ``log_time_ns``.

    The schema is the ``ros2msg`` definition with its dependencies, as rosbag2 writes it; the
    channel's ``offered_qos_profiles`` is map_server's (``MAP_QOS_PROFILES``). The same message and
    time give the same bytes.
    """
    out = io.BytesIO()
    writer = Writer(out, compression=CompressionType.ZSTD)
    writer.start(profile="ros2", library="fuzzyrisk")
    channel = ros2_channel(writer, msgtype=OCCUPANCY_GRID, topic=topic, qos_profiles=MAP_QOS_PROFILES)
    writer.add_message(channel, log_time=log_time_ns, data=cdr, publish_time=log_time_ns)
    writer.finish()
    return out.getvalue()


def ros2_channel(writer: Writer, *, msgtype: str, topic: str, qos_profiles: str = DEFAULT_QOS_PROFILES) -> int:
    """Register ``topic`` of ``msgtype`` on an MCAP writer (ROS 2 profile) as rosbag2 does; its channel id.

    The schema is the ``ros2msg`` definition with its dependencies (what Foxglove and rosbags read
    without our typestore), messages are ``cdr``, and ``offered_qos_profiles`` is what ``ros2 bag
    play`` offers when it republishes the topic.
    """
    definition, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    schema = writer.register_schema(name=msgtype, encoding="ros2msg", data=definition.encode())
    return writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schema,
                                   metadata={"offered_qos_profiles": qos_profiles})
