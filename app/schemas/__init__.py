"""Request and response bodies of the HTTP contract (DESIGN.md section 7).

Shapes and simple bounds are checked here (finite numbers, lengths, ranges);
checks that need a map (dimensions, bounds, limits) live in ``services``.
The OpenAPI examples are real requests: ``tests/app/test_openapi.py`` pastes them.
"""

from __future__ import annotations

import math
import re
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    FiniteFloat,
    PlainValidator,
    StringConstraints,
    Tag,
    model_validator,
)

from app.schemas import engine_choice
from app.errors import ErrorBody
from fuzzyocc.presets import PRESETS
from planning.field import DEFAULT_MAX_RISK

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_NAME_RE = re.compile(NAME_PATTERN)
NAME_RULE = "1 to 64 characters from A-Z a-z 0-9 _ . -, starting with a letter or a digit"


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

# ---------------------------------------------------------------- examples (a session that works)

EXAMPLE_MAP = {
    "name": "lab",
    "dimensions": 2,
    "resolution": 0.05,
    "origin": [-8.0, -5.0],
    "size": [16.0, 10.0],
    "model": "fuzzy",
    "sensor": {"range_sigma": 0.03, "registration_sigma": 0.0},
    "engine": "paper",
}
#: The smallest useful engine: empty, unknown, occupied (Table 1 cut down to three labels).
EXAMPLE_ENGINE = {
    "labels": ["EMP", "UNK", "OCC"],
    "unknown": "UNK",
    "input_mfs": {
        "EMP": {"type": "left_shoulder", "top_end": -2.0, "zero_at": 0.0},
        "OCC": {"type": "triangle", "left": -2.0, "peak": 0.0, "right": 1.5},
        "UNK": {"type": "right_shoulder", "zero_at": 0.0, "top_start": 1.5},
    },
    "output_mfs": {
        "EMP": {"type": "left_shoulder", "top_end": 0.0, "zero_at": 0.5},
        "UNK": {"type": "triangle", "left": 0.0, "peak": 0.5, "right": 1.0},
        "OCC": {"type": "right_shoulder", "zero_at": 0.5, "top_start": 1.0},
    },
    "rules": {
        "EMP": {"EMP": "EMP", "UNK": "EMP", "OCC": "UNK"},
        "UNK": {"EMP": "EMP", "UNK": "UNK", "OCC": "OCC"},
        "OCC": {"EMP": "UNK", "UNK": "OCC", "OCC": "OCC"},
    },
    "and_op": "min",
    "or_op": "max",
    "normalize": False,
}
EXAMPLE_MAP_3D = {
    "name": "hall3d",
    "dimensions": 3,
    "resolution": 0.1,
    "origin": [-5.0, -5.0, 0.0],
    "size": [10.0, 10.0, 3.0],
    "model": "bayes",
    "sensor": {"range_sigma": 0.05, "registration_sigma": 0.01},
}
EXAMPLE_LASER = {
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
EXAMPLE_PLAN = {
    "start": [-1.0, 0.0],
    "goal": [2.0, 0.0],
    "state_space": "R2",
    "planner": "RRTstar",
    "time_limit": 1.0,
    "robot_radius": 0.2,
    "max_risk": DEFAULT_MAX_RISK,
    "risk_weight": 1.0,
    "allow_unknown": True,
    "seed": 1,
}

# ---------------------------------------------------------------- fuzzy engines
# These models document the object form of ``MapCreate.engine`` in the OpenAPI document;
# the request is checked by ``engine_choice.parse`` (``fuzzyocc.engine_spec``), whose messages name
# the bad field by its path (``engine.input_mfs.PO.peak must be a finite number``).

LabelName = Annotated[str, Field(min_length=1, max_length=engine_choice.MAX_NAME_CHARS)]


class TriangleIn(BaseModel):
    """0 at ``left``, 1 at ``peak``, 0 at ``right``; ``left < peak < right``."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["triangle"]
    left: FiniteFloat
    peak: FiniteFloat
    right: FiniteFloat


class TrapezoidIn(BaseModel):
    """0 at ``a``, 1 from ``b`` to ``c``, 0 at ``d``; ``a < b <= c < d``."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["trapezoid"]
    a: FiniteFloat
    b: FiniteFloat
    c: FiniteFloat
    d: FiniteFloat


class LeftShoulderIn(BaseModel):
    """1 up to ``top_end``, 0 from ``zero_at``; ``top_end < zero_at``."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["left_shoulder"]
    top_end: FiniteFloat
    zero_at: FiniteFloat


class RightShoulderIn(BaseModel):
    """0 up to ``zero_at``, 1 from ``top_start``; ``zero_at < top_start``."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["right_shoulder"]
    zero_at: FiniteFloat
    top_start: FiniteFloat


MembershipIn = Annotated[TriangleIn | TrapezoidIn | LeftShoulderIn | RightShoulderIn, Field(discriminator="type")]
LabelMap = Annotated[dict[LabelName, MembershipIn], Field(min_length=2, max_length=engine_choice.MAX_LABELS)]


class EngineDefinition(BaseModel):
    """A fuzzy engine (``fuzzyocc.FuzzyEngine``): labels, membership functions, rule table, operators."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [EXAMPLE_ENGINE]})

    labels: Annotated[list[LabelName], Field(min_length=2, max_length=engine_choice.MAX_LABELS)] = Field(
        description="state and output labels in increasing order of risk"
    )
    unknown: LabelName = Field(description="the label of unknown space (a new cell); alone it defuzzifies to 0.5")
    input_mfs: LabelMap = Field(
        description="per label, on the distance from the measured surface in sigmas (negative: in front); together "
        "they cover the whole axis, and far behind the surface only the unknown label is active, at 1"
    )
    output_mfs: LabelMap = Field(
        description="per label, on the risk axis [0, 1], which they cover; each label alone defuzzifies above "
        "the one before it; at most two positive at any risk"
    )
    rules: dict[LabelName, dict[LabelName, LabelName]] = Field(
        description="rules[current][new]: the label concluded from the cell's current label and the new "
        "measurement's; rules[x][unknown] must be x"
    )
    and_op: Literal["min", "product"] = "min"
    or_op: Literal["max", "probsum"] = "max"
    normalize: bool | None = Field(None, description="rescale each fused state to a largest activation of 1; "
                                   "null: when and_op is product")
    incidence_floor: float = Field(1.0, gt=0.0, le=1.0, description="sigma along a LaserScan beam is divided by "
                                   "max(sin(incidence on the surface), incidence_floor); 1: incidence ignored")
    no_return_neighbours: int = Field(0, ge=0, le=8, description="a LaserScan no-return with a hit among this "
                                      "many neighbours on each side clears only up to 0.1 m before the nearest "
                                      "of them; 0: every no-return clears to range_max")


EnginePreset = Literal[tuple(PRESETS)]  # type: ignore[valid-type]

#: ``MapCreate.engine``: validated (and built) by ``engine_choice.parse``, documented as a preset or an EngineDefinition.
EngineField = Annotated[
    engine_choice.EngineChoice | None,
    PlainValidator(engine_choice.parse, json_schema_input_type=EnginePreset | EngineDefinition | None),
]


class EngineInfo(BaseModel):
    """A fuzzy map's engine."""

    preset: str | None = Field(description="the preset the engine equals, or null")
    definition: dict[str, Any] = Field(description="the engine in full, as an EngineDefinition (the form "
                                       "POST /maps takes)")


# ---------------------------------------------------------------- maps


class SensorIn(BaseModel):
    """Range noise of the sensor and of the pose it is registered with (metres)."""

    model_config = ConfigDict(extra="forbid")

    range_sigma: NonNegativeFinite = 0.03
    registration_sigma: NonNegativeFinite = 0.0
    range_sigma_per_m: NonNegativeFinite = 0.0


class MapCreate(BaseModel):
    """A new map: a box of cells in its ROS frame (``frame_id``; origin = corner of cell 0, as in a Nav2 YAML)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [EXAMPLE_MAP, EXAMPLE_MAP_3D]})

    name: MapName
    dimensions: Literal[2, 3] | None = Field(None, description="2 or 3; taken from len(origin) when left out")
    resolution: PositiveFinite = Field(description="cell edge, metres")
    origin: Vector = Field(description="corner of cell 0 [x, y(, z)], metres")
    size: Annotated[list[PositiveFinite], Field(min_length=2, max_length=3)] = Field(
        description="extent [sx, sy(, sz)], metres, rounded up to whole cells"
    )
    model: Literal["fuzzy", "bayes"] = "fuzzy"
    sensor: SensorIn = Field(default_factory=SensorIn)
    engine: EngineField = Field(
        None, description="fuzzy maps: a preset name, or an EngineDefinition; left out: the default preset"
    )
    frame_id: FrameId = Field(
        DEFAULT_FRAME_ID, description="the ROS frame of the map (a fleet's namespaces: robot1/map): the frame_id of "
        "its OccupancyGrid and of its plans' paths; " + FRAME_ID_RULE,
        json_schema_extra={"pattern": FRAME_ID_PATTERN, "maxLength": FRAME_ID_MAX_CHARS},
    )

    @model_validator(mode="after")
    def _dimensions_agree(self) -> MapCreate:
        dims = self.dimensions or len(self.origin)
        if len(self.origin) != dims:
            raise ValueError(f"origin has {len(self.origin)} values but dimensions is {dims}")
        if len(self.size) != dims:
            raise ValueError(f"size has {len(self.size)} values but origin has {dims}")
        self.dimensions = dims  # type: ignore[assignment]
        return self

    @model_validator(mode="after")
    def _engine_is_fuzzy(self) -> MapCreate:
        if self.engine is not None and self.model != "fuzzy":
            raise ValueError(f"engine applies to fuzzy maps only; a {self.model} map has none: leave engine out")
        return self


class MapInfo(BaseModel):
    """A map as the service holds it."""

    name: str
    dimensions: int
    resolution: float
    origin: list[float]
    size: list[float] = Field(description="extent as built, shape x resolution (the requested size rounded up "
                              "to whole cells), metres: the map covers origin .. origin + size")
    shape: list[int] = Field(description="cells along x, y(, z)")
    model: Literal["fuzzy", "bayes"]
    sensor: SensorIn
    engine: EngineInfo | None = Field(description="the fuzzy engine; null for a bayes map")
    frame_id: str = Field(description="the map's ROS frame (maps made before frames could be chosen: map)")
    scans_fused: int
    version: int = Field(description="grows with every accepted scan batch: by one, except after a batch that "
                         "failed inside the service after it was stored (its number is not reused)")
    created: datetime
    updated: datetime


# ---------------------------------------------------------------- scans

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
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(
                f"orientation must be a unit quaternion [qx, qy, qz, qw] (ROS order), its norm is {norm:.6g}"
            )
        return self


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
    header: dict[str, Any] | None = None


class PointCloudIn(BaseModel):
    """Points in the sensor frame with the sensor pose (3-D maps: Pose3D; 2-D maps: [x, y] points, Pose2D)."""

    model_config = ConfigDict(extra="forbid")

    pose: Pose3D | Pose2D
    points: Annotated[list[Annotated[list[float | None], Field(min_length=2, max_length=3)]], Field(min_length=1)] = (
        Field(description="sensor frame, metres; rows holding null/NaN/inf are dropped (no return)")
    )
    range_max: PositiveFinite
    registration_sigma: NonNegativeFinite = 0.0
    header: dict[str, Any] | None = None


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


#: Query parameters of a binary scan upload (``POST /maps/{name}/scans``).
SCAN_QUERY_FIELDS = (
    "x", "y", "z", "theta", "qx", "qy", "qz", "qw", "angle_min", "angle_increment", "range_min", "range_max",
    "registration_sigma", "point_step",
)
SCAN_QUERY_DOC = "binary uploads only; see the description"


class ScanQuery(BaseModel):
    """The query of ``POST /maps/{name}/scans``: pose and scan parameters of a binary upload.

    Validated with the body (off the event loop for a big body) rather than as 13 separate
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


class BatchResult(BaseModel):
    """What one accepted batch did; ``version`` is the map's version after it."""

    scans_fused: int
    rays: int
    cells_updated: int
    version: int


class BagImportResult(BaseModel):
    """What an imported bag did to the map: every batch (``complete``), or the batches before the one that failed."""

    complete: bool = Field(description="true: every placed scan was fused. false: the import stopped at a batch that "
                           "failed (`stopped`); the batches before it are applied and durable, so do not send the "
                           "bag again (its first part would be fused twice)")
    stopped: ErrorBody | None = Field(None, description="why the import stopped part-way (the error body the failed "
                                      "batch would have answered alone: STORAGE_UNAVAILABLE, NOT_FOUND, CONFLICT, "
                                      "INVALID, ...); null when complete")
    messages: int = Field(description="scan messages read on the topics read")
    scans_fused: int = Field(description="scans fused into the map (all placed ones when complete)")
    skipped: dict[str, int] = Field(description="scan messages left out, by reason")
    rays: int
    cells_updated: int
    batches: int = Field(description="batches applied, each durable before the next")
    version: int = Field(description="the map's version after the last batch applied")
    topics: dict[str, str] = Field(description="the topics read, with their message types")


class LastScan(BaseModel):
    """Beam ends of the last scan fused (world frame, at most 4096, evenly thinned)."""

    origin: list[float]
    endpoints: list[list[float]]
    hit: list[bool] = Field(description="true: the beam hit a surface; false: no return, drawn at range_max")
    version: int


# ---------------------------------------------------------------- risk


class RiskQuery(BaseModel):
    """World points [x, y(, z)] inside the map."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"points": [[1.0, 0.0], [2.99, 0.0]]}]})

    points: Annotated[list[Vector], Field(min_length=1)]


class RiskValues(BaseModel):
    risk: list[float]
    version: int


class RiskGridJSON(BaseModel):
    """The risk grid, indexed ``risk[i][j](k)`` along x, y(, z); cell centre = origin + (index + 0.5) * resolution."""

    name: str
    version: int
    frame_id: str = Field(description="the map's ROS frame, in which origin is given")
    resolution: float
    origin: list[float]
    shape: list[int]
    risk: list[Any] = Field(description="float in [0, 1], rounded to 1e-6 (format=npy for exact float32)")
    observed: list[Any] = Field(description="false where no beam ever reached the cell (unknown)")


# ---------------------------------------------------------------- plans


class PlanRequest(BaseModel):
    """A path query on the map's risk; valid: no observed cell under the robot above ``max_risk``, and never-observed
    cells under it only with ``allow_unknown``."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [EXAMPLE_PLAN]})

    start: Vector = Field(description="[x, y] in R2, [x, y, theta] in SE2/Dubins/ReedsShepp, [x, y, z] in R3")
    goal: Vector
    state_space: str | None = Field(None, description="R2 (default on 2-D maps), SE2, Dubins, ReedsShepp, R3 (3-D)")
    planner: str = "RRTstar"
    time_limit: PositiveFinite = Field(
        1.0, description="seconds; at most FUZZYRISK_MAX_PLAN_TIME_S. A seeded plan is ended by an iteration budget "
        "that fits this on an idle machine, so that it repeats; its clock bound is 3 x time_limit")
    robot_radius: NonNegativeFinite = 0.2
    max_risk: Annotated[float, Field(
        ge=0.0, le=1.0, allow_inf_nan=False,
        description="the most risk an observed cell under the robot may have; default 0.45 (the exports' free "
        "threshold): cells with net free evidence. An observed cell at 0.5 (a surface hit, then seen through as "
        "often) is not free")] = DEFAULT_MAX_RISK
    risk_weight: NonNegativeFinite = 1.0
    allow_unknown: bool = Field(True, description="the robot may overlap never-observed cells (and leave the map), "
                                "whatever max_risk; false: it may not")
    seed: Annotated[int, Field(ge=0, lt=2**32)] | None = None
    turning_radius: PositiveFinite | None = Field(None, description="metres; required by Dubins and ReedsShepp")
    goal_tolerance: PositiveFinite | None = Field(None, description="reach the goal within this; default one cell")
    goal_yaw: FiniteFloat | None = Field(
        None, description="R2 and R3: the yaw (radians, REP 103) of the answer's last pose, as Nav2 gives the last "
        "pose the goal's orientation; left out: the heading of the path's last step. SE2, Dubins and ReedsShepp "
        "take the goal's yaw as its third value instead")


class PlanResult(BaseModel):
    status: Literal["exact", "approximate", "none"]
    path: list[list[float]]
    length: float | None
    max_risk: float | None
    mean_risk: float | None
    cost: float | None
    planner: str
    state_space: str
    planning_time: float
    message: str = Field("", description="empty, or why the status is not exact")
    error_code: Literal["TIMEOUT", "NO_VALID_PATH"] | None = Field(
        None,
        description="null when status is exact; else Nav2's ComputePathToPose name for why not: TIMEOUT (a "
        "sampling planner's time limit, or a seeded plan's iteration budget, ended the search before it reached the "
        "goal) or NO_VALID_PATH (the grid "
        "planner's complete search found no path, or no candidate path passed verification)",
    )
    stopped_by: Literal["complete", "solution", "iterations", "time_limit"] = Field(
        description="what ended the search: the grid search ran to its end (complete), a planner that stops at its "
        "first solution found one (solution), the iteration budget ran out (iterations: a seeded plan's, which "
        "makes it repeat), or the clock did (time_limit; a seeded plan's clock bound is 3 x time_limit)",
    )
    iterations: int = Field(description="planner iterations where the planner counts them, else 0")
    first_solution_time: float | None = Field(
        description="seconds until the planner first held a path (null without one)")
    version: int = Field(description="the map version planned on")
    header: Header = Field(
        description="nav_msgs/Path header: frame_id is the map's frame; stamp is when the service took the plan "
        "up (its clock as ROS time: Unix seconds and nanoseconds), as Nav2's planners stamp a path when they start it")
    poses: list[PoseStamped] = Field(
        description="nav_msgs/Path poses (with header, this answer is a nav_msgs/Path as rosbridge and Foxglove "
        "write it in JSON): one per path point, each with the path's header; z = 0 on 2-D maps; orientation a yaw "
        "about +z (REP 103): SE2, Dubins, ReedsShepp the planned yaw; R2 and R3 the heading of the step to the next "
        "point over the ground (no pitch), the last pose that of the step before it, or goal_yaw when given")


# ---------------------------------------------------------------- nav_msgs (OccupancyGrid, Path)


class Point(BaseModel):
    x: float
    y: float
    z: float


class Quaternion(BaseModel):
    x: float
    y: float
    z: float
    w: float


class PoseMsg(BaseModel):
    position: Point
    orientation: Quaternion


class Time(BaseModel):
    sec: int
    nanosec: int


class Header(BaseModel):
    stamp: Time
    frame_id: str


class PoseStamped(BaseModel):
    """``geometry_msgs/PoseStamped``."""

    header: Header
    pose: PoseMsg


class MapMetaData(BaseModel):
    map_load_time: Time
    resolution: float
    width: int
    height: int
    origin: PoseMsg


class OccupancyGrid(BaseModel):
    """``nav_msgs/OccupancyGrid``: ``data[j * width + i]`` for cell (i, j) from the origin, -1 unknown.

    ``header.stamp`` and ``info.map_load_time`` are the time of the map's last batch (its creation
    before one): every read of one version is the same document. ``version`` is not a message field.
    """

    header: Header
    info: MapMetaData
    data: list[int]
    version: int = Field(description="the map version (not part of the ROS message: drop it before publishing)")


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    """Whether the service is ready for traffic (``GET /ready``: 200 when ``status`` is ready, else 503)."""

    status: Literal["ready", "starting", "failed"] = Field(
        description="ready: maps loaded, kernels compiled, planner workers up; starting: not yet; failed: see detail"
    )
    maps_loaded: int = Field(description="maps held (all stored maps are loaded before the service answers at all)")
    maps_quarantined: list[str] = Field(
        default_factory=list,
        description="stored maps set aside at start because their rows are damaged (a checksum fails, a batch "
        "cannot be decoded): each answers 503 with the reason until dropped (DELETE) or the database is restored",
    )
    kernels_compiled: bool = Field(description="the fusion kernels are compiled, or loaded from numba's cache")
    planner_workers_ready: int = Field(description="planner workers started and warmed up")
    planner_workers_wanted: int = Field(
        description="planner workers readiness waits for: FUZZYRISK_PLAN_WORKERS, or 0 when FUZZYRISK_PLAN_WARMUP "
        "is false (they start at the first plan)"
    )
    batches_in_line: int = Field(
        0, description="scan batches accepted or still arriving and not yet applied, over all maps held (each map "
        "holds at most FUZZYRISK_MAX_PENDING_BATCHES): a backlog that grows means fusion does not keep up"
    )
    longest_fusion_job_s: float = Field(
        0.0, description="how long the oldest job in a fusion thread (a batch's fusion, a snapshot, a map's load) "
        "has run so far, in seconds; 0 when they are idle"
    )
    detail: str = Field("", description="what failed, when status is failed")


class PlannerInfo(BaseModel):
    """One planner a plan request may name."""

    name: str
    optimizing: bool = Field(description="anytime optimizer: uses the whole time limit to lower the cost")


class Planners(BaseModel):
    """What ``POST /maps/{name}/plan`` accepts in ``planner`` and ``state_space``."""

    planners: list[PlannerInfo]
    state_spaces: list[str]
