"""A plan: the query (``PlanRequest``), the answer (``PlanResult``, a ``nav_msgs/Path`` with the plan's measures),
and what a query may name (``Planners``); a path checked under a plan's rules (``PathCheckRequest``,
``PathCheckResult``). ``PathRules`` are what both are held to.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, create_model, model_validator

from app.schemas.common import Header, PoseStamped, Vector
from planning.budget import SEEDED_CLOCK_FACTOR
from planning.field import DEFAULT_MAX_RISK
from planning.parameters import (
    DEFAULT_ALLOW_UNKNOWN,
    DEFAULT_PLANNER,
    DEFAULT_RISK_WEIGHT,
    DEFAULT_ROBOT_RADIUS,
    DEFAULT_TIME_LIMIT,
    GOAL_TOLERANCE,
    MAX_RISK,
    RISK_WEIGHT,
    ROBOT_RADIUS,
    SEEDS,
    TIME_LIMIT,
    TURNING_RADIUS,
    Number,
)
from planning.result import RESULT_ERROR_CODES, PathCheck
from planning.result import PlanResult as PlannerResult

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


def _within(number: Number) -> Any:
    """The pydantic constraints of a ``plan`` parameter's range (``planning.parameters``)."""
    bounds: dict[str, float] = {"gt" if number.low_open else "ge": number.low}
    if number.high < math.inf:
        bounds["le"] = number.high
    return Field(allow_inf_nan=False, **bounds)


class PathRules(BaseModel):
    """What a path is held to and how it is costed, a plan's and a path check's alike: the robot's footprint, the risk
    bound, unknown space, the weight of risk in the cost, and the state space its points are in."""

    state_space: str | None = Field(None, description="R2 (default on 2-D maps), SE2, Dubins, ReedsShepp, R3 (3-D)")
    robot_radius: Annotated[float, _within(ROBOT_RADIUS)] = Field(
        DEFAULT_ROBOT_RADIUS, description="metres: the robot is a disk (a ball in 3-D)")
    max_risk: Annotated[float, _within(MAX_RISK), Field(
        description=f"the most risk an observed cell under the robot may have; default {DEFAULT_MAX_RISK:g} (the "
        "exports' free threshold): cells with net free evidence. An observed cell at 0.5 (a surface hit, then seen "
        "through as often) is not free")] = DEFAULT_MAX_RISK
    risk_weight: Annotated[float, _within(RISK_WEIGHT)] = Field(
        DEFAULT_RISK_WEIGHT, description="cost = length + risk_weight x the integral of risk along the path "
        "(never-observed cells count 0.5)")
    allow_unknown: bool = Field(DEFAULT_ALLOW_UNKNOWN, description="the robot may overlap never-observed cells (and "
                                "leave the map), whatever max_risk; false: it may not")


class PlanRequest(PathRules):
    """A path query on the map's risk; valid: no observed cell under the robot above ``max_risk``, and never-observed
    cells under it only with ``allow_unknown``."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [EXAMPLE_PLAN]})

    start: Vector = Field(description="[x, y] in R2, [x, y, theta] in SE2/Dubins/ReedsShepp, [x, y, z] in R3")
    goal: Vector
    planner: str = DEFAULT_PLANNER
    time_limit: Annotated[float, _within(TIME_LIMIT)] = Field(
        DEFAULT_TIME_LIMIT, description="seconds; at most FUZZYRISK_MAX_PLAN_TIME_S. A seeded plan is ended by an "
        "iteration budget that fits this on an idle machine, so that it repeats; its clock bound is "
        f"{SEEDED_CLOCK_FACTOR:g} x time_limit")
    seed: Annotated[int, Field(ge=SEEDS.start, lt=SEEDS.stop)] | None = None
    turning_radius: Annotated[float, _within(TURNING_RADIUS)] | None = Field(
        None, description="metres; required by Dubins and ReedsShepp")
    goal_tolerance: Annotated[float, _within(GOAL_TOLERANCE)] | None = Field(
        None, description="reach the goal within this; default one cell")
    goal_yaw: FiniteFloat | None = Field(
        None, description="R2 and R3: the yaw (radians, REP 103) of the answer's last pose, as Nav2 gives the last "
        "pose the goal's orientation; left out: the heading of the path's last step. SE2, Dubins and ReedsShepp "
        "take the goal's yaw as its third value instead")


#: How the answer carries the fields of ``planning.PlanResult`` (``PlanResult.to_json``) where its JSON type is
#: not the field's own (``None``: it is), and what the API says of them. The fields and their order are the
#: dataclass's.
_AS_ANSWERED: dict[str, tuple[Any, Any]] = {
    "path": (list[list[float]], ...),
    # the measures are NaN without a path; JSON has no NaN
    "length": (float | None, ...),
    "max_risk": (float | None, ...),
    "mean_risk": (float | None, ...),
    "cost": (float | None, ...),
    "message": (None, Field("", description="empty, or why the status is not exact")),
    "iterations": (None, Field(description="planner iterations where the planner counts them, else 0")),
    "first_solution_time": (float | None, Field(
        description="seconds until the planner first held a path (null without one)")),
    "error_code": (Literal[RESULT_ERROR_CODES] | None, Field(  # type: ignore[valid-type]
        None,
        description="null when status is exact; else Nav2's ComputePathToPose name for why not: TIMEOUT (a "
        "sampling planner's time limit, or a seeded plan's iteration budget, ended the search before it reached the "
        "goal) or NO_VALID_PATH (the grid "
        "planner's complete search found no path, or no candidate path passed verification)",
    )),
    "stopped_by": (None, Field(
        description="what ended the search: the grid search ran to its end (complete), a planner that stops at its "
        "first solution found one (solution), the iteration budget ran out (iterations: a seeded plan's, which "
        "makes it repeat), or the clock did (time_limit; a seeded plan's clock bound is "
        f"{SEEDED_CLOCK_FACTOR:g} x time_limit)",
    )),
}


def _answer_fields(answer: type, as_answered: dict[str, tuple[Any, Any]]) -> dict[str, Any]:
    """The fields of the dataclass ``answer`` as pydantic field definitions, as ``as_answered`` has them."""
    types = typing.get_type_hints(answer)
    names = [f.name for f in dataclasses.fields(answer)]
    if unknown := set(as_answered) - set(names):
        raise TypeError(f"{sorted(unknown)} are not fields of {answer.__module__}.{answer.__qualname__}")
    definitions = {}
    for name in names:
        wire, field = as_answered.get(name, (None, ...))
        definitions[name] = (types[name] if wire is None else wire, field)
    return definitions


#: What the planner answered, field by field (``PlanResult.to_json``).
_PlannerAnswer: type[BaseModel] = create_model("_PlannerAnswer", **_answer_fields(PlannerResult, _AS_ANSWERED))


class PlanResult(_PlannerAnswer):  # type: ignore[misc,valid-type]
    # the planner's answer, and the map version and nav_msgs/Path the service adds
    version: int = Field(description="the map version planned on")
    header: Header = Field(
        description="nav_msgs/Path header: frame_id is the map's frame; stamp is when the service took the plan "
        "up (its clock as ROS time: Unix seconds and nanoseconds), as Nav2's planners stamp a path when they start it")
    poses: list[PoseStamped] = Field(
        description="nav_msgs/Path poses (with header, this answer is a nav_msgs/Path as rosbridge and Foxglove "
        "write it in JSON): one per path point, each with the path's header; z = 0 on 2-D maps; orientation a yaw "
        "about +z (REP 103): SE2, Dubins, ReedsShepp the planned yaw; R2 and R3 the heading of the step to the next "
        "point over the ground (no pitch), the last pose that of the step before it, or goal_yaw when given")


EXAMPLE_PATH_CHECK = {
    "path": [[-1.0, 0.0], [0.5, 0.0], [2.0, 0.0]],
    "robot_radius": 0.2,
    "max_risk": DEFAULT_MAX_RISK,
    "allow_unknown": True,
}


class PathCheckRequest(PathRules):
    """A path to check on the map's current risk, as ``path`` or as a ``nav_msgs/Path``'s ``poses``, under the rules a
    plan is held to."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [EXAMPLE_PATH_CHECK]})

    path: Annotated[list[Vector], Field(min_length=1)] | None = Field(
        None, description="the points, as a plan answers them: [x, y] in R2, [x, y, theta] in SE2/Dubins/ReedsShepp "
        "(theta is not checked: the robot is a disk), [x, y, z] in R3; joined by straight segments. A curved motion "
        "is sent as the dense points a plan returns for it. At most FUZZYRISK_MAX_PATH_POINTS")
    poses: Annotated[list[PoseStamped], Field(min_length=1)] | None = Field(
        None, description="or the path as a nav_msgs/Path's poses, as a plan answers them: their positions (z only "
        "on 3-D maps) and, in SE2/Dubins/ReedsShepp, the yaw of their orientations. Every frame_id given must be "
        "the map's")
    header: Header | None = Field(
        None, description="a nav_msgs/Path's header, so that a whole Path may be sent: its frame_id, when given, "
        "must be the map's")

    @model_validator(mode="after")
    def _one_path(self) -> PathCheckRequest:
        if (self.path is None) == (self.poses is None):
            given = "both were given" if self.path is not None else "neither was given"
            raise ValueError(f"give the path as 'path' (a list of points) or as 'poses' (a nav_msgs/Path's): {given}")
        if self.header is not None and self.path is not None:
            raise ValueError("header goes with poses (a nav_msgs/Path), not with path")
        return self


#: How a path check answers the fields of ``planning.PathCheck``.
_CHECK_AS_ANSWERED: dict[str, tuple[Any, Any]] = {
    "valid": (None, Field(description="every cell every segment crosses is valid for the robot, and every point "
                                      "lies on the map")),
    "first_invalid_index": (None, Field(
        description="the index of the first point whose segment to the next point is invalid (or leaves the map), "
        "or of the point itself when the path is that one point; null when valid")),
    "max_risk": (None, Field(description="the largest risk under the robot along the path (never-observed cells "
                                         "count 0.5), as a plan reports it; null when a point lies off the map")),
    "cost": (None, Field(description="length + risk_weight x the integral of that risk along the path, as a plan "
                                     "computes its cost; null when a point lies off the map")),
    "length": (None, Field(description="metres; null when a point lies off the map")),
}


#: What the check answered, field by field (``planning.PathCheck``).
_PathCheckAnswer: type[BaseModel] = create_model("_PathCheckAnswer", **_answer_fields(PathCheck, _CHECK_AS_ANSWERED))


class PathCheckResult(_PathCheckAnswer):  # type: ignore[misc,valid-type]
    """A path held to a plan's rules on one version of the map (Nav2's IsPathValid), measured as a plan is."""

    version: int = Field(description="the map version checked on")


class PlannerInfo(BaseModel):
    """One planner a plan request may name."""

    name: str
    optimizing: bool = Field(description="anytime optimizer: uses the whole time limit to lower the cost")


class Planners(BaseModel):
    """What ``POST /maps/{name}/plan`` accepts in ``planner`` and ``state_space``."""

    planners: list[PlannerInfo]
    state_spaces: list[str]
