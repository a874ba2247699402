"""A ``nav_msgs/Path`` in (rosbridge's JSON shape, as a plan answers it): its poses as the points of a path in a
state space's layout, and its frames held to the map's."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from app.errors import Invalid
from app.ros.messages_out import YAW_SPACES
from app.schemas import Header, PoseStamped, Quaternion


def yaw_of(q: Quaternion) -> float:
    """The rotation about +z of an orientation (REP 103), radians; from the quaternion as given, unit or not."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), q.w * q.w + q.x * q.x - q.y * q.y - q.z * q.z)


def path_points(poses: Sequence[PoseStamped], state_space: str) -> np.ndarray:
    """The poses as a path's points, as a plan request's ``start`` has them: [x, y] in R2, [x, y, yaw] in SE2, Dubins
    and ReedsShepp, [x, y, z] in R3 (z is left out on a 2-D map, as Nav2 leaves it)."""
    if state_space in YAW_SPACES:
        return np.array([(p.pose.position.x, p.pose.position.y, yaw_of(p.pose.orientation)) for p in poses])
    if state_space == "R3":
        return np.array([(p.pose.position.x, p.pose.position.y, p.pose.position.z) for p in poses])
    return np.array([(p.pose.position.x, p.pose.position.y) for p in poses])


def check_frames(map_frame: str, header: Header | None, poses: Sequence[PoseStamped]) -> None:
    """``Invalid`` naming the first header whose ``frame_id`` is given and is not the map's (an empty one is the
    path's, as ROS reads it)."""
    named = [("header", header)] if header is not None else []
    named += [(f"poses[{k}].header", pose.header) for k, pose in enumerate(poses)]
    for name, head in named:
        if head.frame_id not in ("", map_frame):
            raise Invalid(f"{name}.frame_id {head.frame_id[:80]!r} is not the map's frame {map_frame!r}: send the "
                          "path in the map's frame (tf2 can transform it)")
