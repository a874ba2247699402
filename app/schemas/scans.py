"""Scans in (a JSON batch of LaserScans and point clouds, a binary upload's query) and what a batch did."""

from __future__ import annotations

import math
from typing import Annotated, Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    FiniteFloat,
    StringConstraints,
    Tag,
    model_validator,
)

from app.schemas.common import NonNegativeFinite, PositiveFinite, StampIn, ns_of_ros_time
from fuzzyocc.tf import UNIT_QUATERNION_TOLERANCE

EXAMPLE_LASER = {
    "header": {"stamp": {"sec": 1796614484, "nanosec": 690952830}, "frame_id": "laser"},
    "pose": {"x": 0.0, "y": 0.0, "theta": 0.0},
    "angle_min": -0.6,
    "angle_increment": 0.1,
    "ranges": [3.1, 3.05, 3.02, 3.0, None, 3.0, 3.0, "inf", 3.02, 3.05, 3.1, 3.16, 3.23],
    "range_min": 0.1,
    "range_max": 30.0,
}
EXAMPLE_CLOUD = {
    "pose": {"position": [0.0, 0.0, 1.0], "orientation": [0.0, 0.0, 0.0, 1.0]},
    "points": [[3.0, -0.5, 0.0], [3.0, 0.0, 0.0], [3.0, 0.5, 0.2], [2.5, 1.0, -0.5]],
    "range_max": 30.0,
}


#: JSON has no inf or NaN: a range may also be null (skipped, like NaN) or one of these strings:
#: inf, +inf, -inf, Infinity, +Infinity, -Infinity, nan, NaN. A pattern rather than an enum: client
#: generators name enum members by upper-casing them, and "nan" and "NaN" would collide.
RANGE_TOKEN_PATTERN = r"^([+-]?(inf|Infinity)|nan|NaN)$"
RangeToken = Annotated[str, StringConstraints(pattern=RANGE_TOKEN_PATTERN)]
RangeValue = float | None | RangeToken


class Pose2D(BaseModel):
    """Planar pose of the sensor in the map frame: metres and radians, yaw counter-clockwise."""

    model_config = ConfigDict(extra="forbid")

    x: FiniteFloat
    y: FiniteFloat
    theta: FiniteFloat


class Pose3D(BaseModel):
    """Sensor pose in the map frame: position [x, y, z] and unit quaternion [qx, qy, qz, qw]."""

    model_config = ConfigDict(extra="forbid")

    position: Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]
    orientation: Annotated[list[FiniteFloat], Field(min_length=4, max_length=4)]

    @model_validator(mode="after")
    def _unit_quaternion(self) -> Pose3D:
        norm = math.sqrt(sum(q * q for q in self.orientation))
        if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
            raise ValueError(
                f"orientation must be a unit quaternion [qx, qy, qz, qw] (ROS order), its norm is {norm:.6g}"
            )
        return self


class ScanHeader(BaseModel):
    """A scan's ``std_msgs/Header``: ``stamp`` is when it was taken; ``frame_id`` (the sensor's frame) is not used, the
    pose places the scan."""

    stamp: StampIn | None = Field(
        None, description="ROS time (Unix sec and nanosec) the scan was taken, kept with it (GET "
        "/maps/{name}/trajectory); left out: the time the service received the batch, on its clock")
    frame_id: str | None = None

    def stamp_ns(self) -> int | None:
        """The stamp as Unix nanoseconds, or None."""
        return None if self.stamp is None else ns_of_ros_time(self.stamp)


class LaserScanIn(BaseModel):
    """A ``sensor_msgs/LaserScan``: beam i points at ``angle_min + i * angle_increment`` (REP 117 ranges)."""

    model_config = ConfigDict(extra="forbid")

    pose: Pose2D
    angle_min: FiniteFloat
    angle_increment: FiniteFloat
    ranges: Annotated[list[RangeValue], Field(min_length=1)] = Field(
        description="metres; null/NaN/-inf/below range_min are skipped, +inf or >= range_max mean no return"
    )
    range_min: NonNegativeFinite
    range_max: PositiveFinite
    registration_sigma: NonNegativeFinite = Field(0.0, description="extra pose uncertainty of this scan, metres")
    # accepted and ignored so that a converted ROS message can be posted as it is
    angle_max: float | None = None
    time_increment: float | None = None
    scan_time: float | None = None
    intensities: list[float | None] | None = None
    header: ScanHeader | None = None


class PointCloudIn(BaseModel):
    """Points in the sensor frame with the sensor pose (3-D maps: Pose3D; 2-D maps: [x, y] points, Pose2D)."""

    model_config = ConfigDict(extra="forbid")

    pose: Pose3D | Pose2D
    points: Annotated[list[Annotated[list[float | None], Field(min_length=2, max_length=3)]], Field(min_length=1)] = (
        Field(description="sensor frame, metres; rows holding null/NaN/inf are dropped (no return)")
    )
    range_max: PositiveFinite
    registration_sigma: NonNegativeFinite = 0.0
    header: ScanHeader | None = None


def _scan_kind(value: Any) -> str | None:
    if isinstance(value, dict):
        return "laser" if "ranges" in value else "cloud" if "points" in value else None
    return "laser" if isinstance(value, LaserScanIn) else "cloud" if isinstance(value, PointCloudIn) else None


ScanIn = Annotated[
    Annotated[LaserScanIn, Tag("laser")] | Annotated[PointCloudIn, Tag("cloud")],
    Discriminator(
        _scan_kind,
        custom_error_type="scan_kind",
        custom_error_message="a scan needs either 'ranges' (a LaserScan) or 'points' (a point cloud)",
    ),
]


class ScanBatch(BaseModel):
    """Scans applied together, in order, all or nothing."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"scans": [EXAMPLE_LASER]}, {"scans": [EXAMPLE_CLOUD]}]},
    )

    scans: Annotated[list[ScanIn], Field(min_length=1)]


SCAN_QUERY_DOC = "binary uploads only; see the description"


class ScanQuery(BaseModel):
    """The query of ``POST /maps/{name}/scans``: pose and scan parameters of a binary upload.

    Validated with the body (off the event loop for a big body) rather than as separate
    FastAPI query parameters, whose per-request resolution cost more than the rest of the
    route; the errors are FastAPI's (``loc: ["query", name]``) and so is the OpenAPI entry
    (``app.api.routes.scans``). Unknown parameters are ignored, as FastAPI does.
    """

    model_config = ConfigDict(extra="ignore")

    x: FiniteFloat | None = None
    y: FiniteFloat | None = None
    z: FiniteFloat | None = None
    theta: FiniteFloat | None = None
    qx: FiniteFloat | None = None
    qy: FiniteFloat | None = None
    qz: FiniteFloat | None = None
    qw: FiniteFloat | None = None
    angle_min: FiniteFloat | None = None
    angle_increment: FiniteFloat | None = None
    range_min: FiniteFloat | None = None
    range_max: FiniteFloat | None = None
    registration_sigma: FiniteFloat | None = None
    # raw float32 points: bytes per point (x, y, z float32 at its start), so a stride is never guessed
    point_step: Annotated[int, Field(ge=12, le=65536)] | None = None


#: Query parameters of a binary scan upload (``POST /maps/{name}/scans``).
SCAN_QUERY_FIELDS = tuple(ScanQuery.model_fields)


class BatchResult(BaseModel):
    """What one accepted batch did; ``version`` is the map's version after it."""

    scans_fused: int
    rays: int
    cells_updated: int
    version: int


class LastScan(BaseModel):
    """Beam ends of the last scan fused (world frame, at most 4096, evenly thinned)."""

    origin: list[float]
    endpoints: list[list[float]]
    hit: list[bool] = Field(description="true: the beam hit a surface; false: no return, drawn at range_max")
    version: int
