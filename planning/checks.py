"""What ``plan`` refuses before any planner runs: arguments out of range, and an unusable start or goal.

A wrong argument raises ValueError naming it; a start or goal outside the map or not valid
raises PlanError with Nav2's code. ``check_path`` holds a path to the same rules, checked here too
(``check_rules``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from planning.field import RiskField
from planning.packed import PackedGrid
from planning.parameters import GOAL_TOLERANCE, MAX_RISK, RISK_WEIGHT, ROBOT_RADIUS, SEEDS, TIME_LIMIT, TURNING_RADIUS
from planning.planners import GRID, PlannerSpec
from planning.result import (
    GOAL_OCCUPIED,
    GOAL_OUTSIDE_MAP,
    START_OCCUPIED,
    START_OUTSIDE_MAP,
    PlanError,
)
from planning.spaces import STATE_SPACES, SpaceSpec

#: Bounds a plan's parameters get from its map (``max_robot_radius``): a robot's dilation may
#: cost at most this many (cell x cell of radius), about 10 s; the risk weight at most this.
MAX_DILATION_WORK = 1e9
MAX_RISK_WEIGHT = 1e4


@dataclass(frozen=True)
class Rules:
    """What a position is held to and what a path costs, checked: the robot's disk, the risk bound, unknown space,
    the weight of risk in the cost."""

    robot_radius: float
    max_risk: float
    risk_weight: float
    allow_unknown: bool


@dataclass(frozen=True)
class Arguments:
    """``plan``'s arguments past the field, planner and state space, checked (the flags as bool)."""

    start: tuple[float, ...]
    goal: tuple[float, ...]
    time_limit: float
    rules: Rules
    seed: int | None
    tolerance: float
    turning_radius: float | None
    max_iterations: int | None
    grid_seed: bool


def max_robot_radius(field: RiskField, diagonal: float) -> float:
    """Half the map's diagonal, and no wider than a dilation of ``MAX_DILATION_WORK`` cell-radii.

    The dilation by the robot (``field.py``) costs about the map's cells times the radius in
    cells (1 s for 1 M cells and 100 cells of radius on 2 cores): a radius of a million metres
    asked for petabytes, so the bound is what the map makes sensible, checked before any work.
    """
    cells = max(1, math.prod(field.shape))
    return min(0.5 * diagonal, field.resolution * max(1.0, MAX_DILATION_WORK / cells))


def check_point(name: str, value: Any, size: int, space: str) -> tuple[float, ...]:
    """``value`` as ``size`` finite floats, the layout of a state of ``space``; ValueError naming ``name``."""
    try:
        pts = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a sequence of {size} numbers, got {value!r}") from None
    if len(pts) != size:
        layout = {"R2": "(x, y)", "R3": "(x, y, z)"}.get(space, "(x, y, theta)")
        raise ValueError(f"{name}: {space} needs {layout}, got {len(pts)} numbers")
    if not all(math.isfinite(v) for v in pts):
        raise ValueError(f"{name}: must be finite, got {value!r}")
    return pts


def space_spec(state_space: str | None, field: RiskField) -> SpaceSpec:
    """The space a plan on ``field`` runs in: ``state_space``, or R2 / R3 by the field's dimension."""
    name = state_space if state_space is not None else ("R3" if field.ndim == 3 else "R2")
    spec = STATE_SPACES.get(name) if isinstance(name, str) else None
    if spec is None:
        raise ValueError(f"state_space: unknown {name!r}; choose one of: {', '.join(STATE_SPACES)}")
    if spec.field_ndim != field.ndim:
        fitting = [s for s, v in STATE_SPACES.items() if v.field_ndim == field.ndim]
        raise ValueError(f"state_space: {name} needs a {spec.field_ndim}-D field, this one is "
                         f"{field.ndim}-D; choose one of: {', '.join(fitting)}")
    return spec


def check_endpoint(grid: PackedGrid, point: tuple[float, ...], which: str, max_risk: float) -> None:
    """Raise PlanError when a start or goal position is outside the map or not valid."""
    position = point[: grid.ndim]
    index = grid.cell_index(position)
    if index is None:
        lo = ", ".join(f"{v:g}" for v in grid.origin)
        hi = ", ".join(f"{o + n * grid.resolution:g}" for o, n in zip(grid.origin, grid.shape, strict=True))
        raise PlanError(
            START_OUTSIDE_MAP if which == "start" else GOAL_OUTSIDE_MAP,
            f"{which} {position} is outside the map [{lo}] .. [{hi}]",
        )
    if grid.valid.reshape(-1)[index]:
        return
    code = START_OCCUPIED if which == "start" else GOAL_OCCUPIED
    risk = float(grid.field.dilated_observed_risk(grid.robot_radius).reshape(-1)[index])
    if risk > max_risk:
        raise PlanError(code, f"{which} {position}: risk of the observed cells under the robot's footprint {risk:.3f} > "
                              f"max_risk {max_risk:g}")
    assert grid.unknown is not None  # only unknown space is left to make the cell invalid
    raise PlanError(
        code,
        f"{which} {position}: the robot's footprint overlaps unknown (never observed) space and "
        f"allow_unknown is false",
    )


def check_rules(field: RiskField, robot_radius: Any, max_risk: Any, risk_weight: Any, allow_unknown: Any) -> Rules:
    """The rules of a plan or a path check on ``field``, checked; ValueError naming the first wrong one."""
    diagonal = math.hypot(*(n * field.resolution for n in field.shape))
    radius = ROBOT_RADIUS.check(robot_radius, high=max_robot_radius(field, diagonal))
    limit = MAX_RISK.check(max_risk)
    weight = RISK_WEIGHT.check(risk_weight, high=MAX_RISK_WEIGHT)
    if not isinstance(allow_unknown, bool | np.bool_):
        raise ValueError(f"allow_unknown: must be a bool, got {allow_unknown!r}")
    return Rules(radius, limit, weight, bool(allow_unknown))


def check_arguments(
    field: RiskField,
    pspec: PlannerSpec,
    sspec: SpaceSpec,
    start: Any,
    goal: Any,
    time_limit: Any,
    robot_radius: Any,
    max_risk: Any,
    risk_weight: Any,
    allow_unknown: Any,
    seed: Any,
    goal_tolerance: Any,
    turning_radius: Any,
    max_iterations: Any,
    grid_seed: Any,
) -> Arguments:
    """``plan``'s arguments checked against the field and state space; ValueError naming the first wrong one."""
    if pspec.make is None and sspec.name not in ("R2", "R3"):
        raise ValueError(f"planner: {GRID!r} plans in R2 and R3 only, not in {sspec.name}")
    time_limit = TIME_LIMIT.check(time_limit)
    rules = check_rules(field, robot_radius, max_risk, risk_weight, allow_unknown)
    diagonal = math.hypot(*(n * field.resolution for n in field.shape))
    tolerance = (
        field.resolution if goal_tolerance is None
        else GOAL_TOLERANCE.check(goal_tolerance, high=diagonal)
    )
    if sspec.curved:
        if turning_radius is None:
            raise ValueError(f"turning_radius: required by {sspec.name}")
        # a turning circle wider than the map cannot turn in it (and OMPL's curves lose precision)
        turning_radius = TURNING_RADIUS.check(turning_radius, high=diagonal)
    if seed is not None and (
        isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not SEEDS.start <= seed < SEEDS.stop
    ):
        raise ValueError(f"seed: must be an integer in [0, 2**32), got {seed!r}")
    if max_iterations is not None and (
        isinstance(max_iterations, bool) or not isinstance(max_iterations, int | np.integer) or max_iterations < 1
    ):
        raise ValueError(f"max_iterations: must be a positive integer, got {max_iterations!r}")
    if not isinstance(grid_seed, bool | np.bool_):
        raise ValueError(f"grid_seed: must be a bool, got {grid_seed!r}")
    start_pt = check_point("start", start, sspec.state_dim, sspec.name)
    goal_pt = check_point("goal", goal, sspec.state_dim, sspec.name)
    return Arguments(start_pt, goal_pt, time_limit, rules, seed, tolerance, turning_radius, max_iterations,
                     bool(grid_seed))
