"""A ``nav_msgs/Path`` in (rosbridge's JSON shape, as a plan answers it): its poses as the points of a path in a
state space's layout, and its frames held to the map's; a corrected trajectory's body read without holding the GIL
for long."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from fastapi.exceptions import RequestValidationError
from pydantic import TypeAdapter, ValidationError

from app.errors import Invalid
from app.ros.messages_out import YAW_SPACES
from app.schemas import CorrectedPath, Header, PoseStamped, Quaternion
from app.schemas.common import located_errors

#: Poses validated in one call: pydantic holds the GIL for a whole call (100,000 poses, 20 MB, took 3 s in
#: one on a loaded 2-core machine), so the event loop and the other threads get it between chunks of 15 ms instead.
_CHUNK_POSES = 256
_POSES = TypeAdapter(CorrectedPath.model_fields["poses"].annotation)
_HEADER = TypeAdapter(CorrectedPath.model_fields["header"].annotation)


def corrected_path(body: bytes) -> CorrectedPath:
    """A ``CorrectedPath`` of a JSON body, validated as the model says, a chunk of poses at a time (run it in a
    parse thread). ``RequestValidationError`` as FastAPI would raise it for the model (``loc`` from ``body``)."""
    try:
        document = json.loads(body)
    except ValueError as exc:
        raise RequestValidationError([{"type": "json_invalid", "loc": ("body",), "msg": f"JSON: {exc}"}]) from None
    if not isinstance(document, dict):
        raise RequestValidationError([{"type": "model_type", "loc": ("body",), "msg": "must be a nav_msgs/Path object"}])
    missing = [key for key in ("header", "poses") if key not in document]
    if missing:
        raise RequestValidationError([{"type": "missing", "loc": ("body", key), "msg": "Field required"}
                                      for key in missing])
    header = _validated(_HEADER, document["header"], ("body", "header"))
    poses = document["poses"]
    if not isinstance(poses, list) or not poses:
        raise RequestValidationError([{"type": "too_short", "loc": ("body", "poses"),
                                       "msg": "must be a list of one pose at least"}])
    validated: list[Any] = []
    for start in range(0, len(poses), _CHUNK_POSES):
        validated += _validated(_POSES, poses[start:start + _CHUNK_POSES], ("body", "poses"), offset=start)
    return CorrectedPath.model_construct(header=header, poses=validated)


def _validated(adapter: TypeAdapter[Any], value: object, where: tuple[Any, ...], offset: int = 0) -> Any:
    try:
        return adapter.validate_python(value)
    except ValidationError as exc:
        raise RequestValidationError(located_errors(exc, where, hidden=(dict, list, str, bytes), offset=offset)) from None


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
