"""The vocabulary several bodies share: map names, ROS frame ids, bounded numbers and vectors, and the
``std_msgs``/``geometry_msgs`` shapes a ``nav_msgs`` answer is made of (``OccupancyGrid``, ``Path``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, FiniteFloat, ValidationError

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_NAME_RE = re.compile(NAME_PATTERN)
NAME_RULE = "1 to 64 characters from A-Z a-z 0-9 _ . -, starting with a letter or a digit"


def located_errors(exc: ValidationError, where: tuple[Any, ...], *, hidden: tuple[type, ...],
                   offset: int = 0) -> list[dict[str, Any]]:
    """pydantic's errors as a ``RequestValidationError`` carries them: each ``loc`` under ``where`` (its first index
    moved by ``offset``: a chunk of a list validated alone), and no ``input`` of the ``hidden`` types (a bad scan's or
    grid's input is all of its numbers, which the answer never echoes)."""
    located = []
    for e in exc.errors(include_url=False):
        loc = list(e["loc"])
        if offset and loc and isinstance(loc[0], int):
            loc[0] += offset
        located.append({k: v for k, v in {**e, "loc": (*where, *loc)}.items()
                        if k != "input" or not isinstance(v, hidden)})
    return located


def check_map_name(name: str) -> str:
    """Return ``name`` when it is a valid map name, else raise ``ValueError`` saying the rule."""
    if not _NAME_RE.fullmatch(name):
        raise ValueError(f"map name {name!r} is not allowed: use {NAME_RULE}")
    return name


MapName = Annotated[str, AfterValidator(check_map_name)]

#: A ROS frame id as tf2 takes it: no leading slash (tf2 refuses one), ROS name tokens joined by single
#: slashes (a fleet's namespaces: ``robot1/map``).
FRAME_ID_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$"
_FRAME_ID_RE = re.compile(FRAME_ID_PATTERN)
FRAME_ID_MAX_CHARS = 256
DEFAULT_FRAME_ID = "map"
FRAME_ID_RULE = ("tokens of A-Z a-z 0-9 _ that start with a letter or _, joined by single '/', with no leading or "
                 f"trailing '/' (tf2 refuses a leading one), at most {FRAME_ID_MAX_CHARS} characters: e.g. "
                 "'map' or 'robot1/map'")


def check_frame_id(frame_id: str) -> str:
    """Return ``frame_id`` when tf2 and ROS name rules accept it, else raise ``ValueError`` saying the rule."""
    if len(frame_id) > FRAME_ID_MAX_CHARS or not _FRAME_ID_RE.fullmatch(frame_id):
        raise ValueError(f"frame_id {frame_id[:80]!r} is not allowed: use {FRAME_ID_RULE}")
    return frame_id


FrameId = Annotated[str, AfterValidator(check_frame_id)]
NonNegativeFinite = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
PositiveFinite = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
Vector = Annotated[list[FiniteFloat], Field(min_length=2, max_length=3)]


# ---------------------------------------------------------------- nav_msgs parts (OccupancyGrid, Path)


class Point(BaseModel):
    x: FiniteFloat
    y: FiniteFloat
    z: FiniteFloat


class Quaternion(BaseModel):
    x: FiniteFloat
    y: FiniteFloat
    z: FiniteFloat
    w: FiniteFloat


class PoseMsg(BaseModel):
    position: Point
    orientation: Quaternion


class Time(BaseModel):
    sec: int
    nanosec: int


NS_PER_S = 1_000_000_000
#: ``builtin_interfaces/Time.sec`` is an int32.
MAX_ROS_SEC = 2**31 - 1


class StampIn(Time):
    """A ``builtin_interfaces/Time`` taken in (a scan's ``header.stamp``): Unix time, never negative (``rclcpp::Time``
    refuses that too), ``nanosec`` below one second, both JSON integers."""

    model_config = ConfigDict(extra="forbid")

    sec: Annotated[int, Field(ge=0, le=MAX_ROS_SEC, strict=True)]
    nanosec: Annotated[int, Field(ge=0, lt=NS_PER_S, strict=True)]


def ros_time_of_ns(nanoseconds: int) -> dict[str, int]:
    """``builtin_interfaces/Time`` of Unix nanoseconds (``time.time_ns()``)."""
    sec, nanosec = divmod(int(nanoseconds), NS_PER_S)
    return {"sec": sec, "nanosec": nanosec}


def ns_of_ros_time(stamp: Mapping[str, int] | Any) -> int:
    """Unix nanoseconds of a ``builtin_interfaces/Time``: a message's stamp (``.sec``, ``.nanosec``) or its JSON dict."""
    if isinstance(stamp, Mapping):
        return int(stamp["sec"]) * NS_PER_S + int(stamp["nanosec"])
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


class Header(BaseModel):
    stamp: Time
    frame_id: str


class PoseStamped(BaseModel):
    """``geometry_msgs/PoseStamped``."""

    header: Header
    pose: PoseMsg


class PathMessage(BaseModel):
    """``nav_msgs/Path`` as rosbridge and Foxglove write it in JSON."""

    header: Header = Field(description="frame_id: the map's frame, in which every pose is given")
    poses: list[PoseStamped] = Field(description="each a geometry_msgs/PoseStamped with a header of its own")
