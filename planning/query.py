"""``plan``: one query, from its arguments to a measured path.

One query, step by step: check the arguments (``checks``); pack the field dilated by the robot
for the kernels; refuse an unusable start or goal with Nav2's codes; then the grid planner's
search, or a sampling planner's solve (``ompl_solve``); interpolate at the map resolution,
verify every crossed cell and measure (``paths``).

Time: ``time_limit`` bounds the whole call in wall-clock time, seeded or not, except the
one-time compilation of the kernels a state space uses (``warming.warm_up``: seconds on a cold
numba cache, tens of milliseconds from the cache), which the first plan of a process in that
space does before its clock starts: otherwise a first plan would spend its time limit in the
compiler and find nothing. How a solve keeps to the limit, and how a seeded plan gives the same
path on a loaded machine: ``ompl_solve``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from planning.checks import check_arguments, check_endpoint, space_spec
from planning.field import DEFAULT_MAX_RISK, RiskField
from planning.grid_search import grid_path
from planning.ompl_solve import CLOCK_NOTE, plan_ompl
from planning.packed import PackedGrid
from planning.parameters import (
    DEFAULT_ALLOW_UNKNOWN,
    DEFAULT_PLANNER,
    DEFAULT_RISK_WEIGHT,
    DEFAULT_ROBOT_RADIUS,
    DEFAULT_TIME_LIMIT,
)
from planning.paths import drop_collinear, interpolate_straight, plan_result
from planning.planners import GRID, planner_spec
from planning.result import NO_VALID_PATH, PlanResult
from planning.spaces import SpaceSpec
from planning.warming import is_warm, warm_up

#: CLOCK_NOTE is ``ompl_solve``'s, named here too for the callers that read it from this module.
__all__ = ["CLOCK_NOTE", "plan"]


def plan(
    field: RiskField,
    start: Sequence[float],
    goal: Sequence[float],
    planner: str = DEFAULT_PLANNER,
    state_space: str | None = None,
    time_limit: float = DEFAULT_TIME_LIMIT,
    robot_radius: float = DEFAULT_ROBOT_RADIUS,
    max_risk: float = DEFAULT_MAX_RISK,
    risk_weight: float = DEFAULT_RISK_WEIGHT,
    allow_unknown: bool = DEFAULT_ALLOW_UNKNOWN,
    seed: int | None = None,
    goal_tolerance: float | None = None,
    turning_radius: float | None = None,
    max_iterations: int | None = None,
    grid_seed: bool = True,
) -> PlanResult:
    """Plan a low-risk path on a risk field.

    Parameters
    ----------
    field : RiskField
        The risk grid; the robot sees it dilated by ``robot_radius`` (see ``field.py``).
    start, goal : sequence of float
        (x, y) in R2, (x, y, theta) in SE2 / Dubins / ReedsShepp, (x, y, z) in R3.
    planner : str
        A name of :func:`available_planners` ("grid" plans in R2 and R3 only).
    state_space : {"R2", "SE2", "Dubins", "ReedsShepp", "R3"} or None
        None: R2 on a 2-D field, R3 on a 3-D one.
    time_limit : float
        Seconds for solving plus simplifying (> 0). The grid planner is not time-bounded. A
        seeded plan is ended by its iteration budget, sized to fit this on an idle machine;
        its clock bound is ``SEEDED_CLOCK_FACTOR`` (3) times this (``planning.wall_clock_limit``).
    robot_radius : float
        Metres, >= 0, at most half the map's diagonal and what a dilation of
        ``checks.MAX_DILATION_WORK`` cell-radii allows on this map.
    max_risk : float
        In [0, 1]: a position is valid when no observed cell under the footprint has a higher risk
        (never-observed cells are ``allow_unknown``'s). The default, 0.45, is the exports' free
        threshold: the robot drives on cells with net free evidence, or on unknown ones.
    risk_weight : float
        In [0, ``checks.MAX_RISK_WEIGHT``]: cost is ``length + risk_weight * integral of dilated risk`` (metres x risk).
    allow_unknown : bool
        True allows positions whose footprint overlaps never-observed cells (or leaves the map),
        whatever ``max_risk`` says; False forbids them.
    seed : int or None
        In [0, 2**32): seeds OMPL and bounds the solve by iterations (see ``ompl_solve``)
        so the same seed gives the same path.
    goal_tolerance : float or None
        Distance (in the state space's metric) within which the goal counts as reached;
        default one cell; at most the map's diagonal.
    turning_radius : float or None
        Metres, > 0 and at most the map's diagonal; required by Dubins and ReedsShepp,
        ignored otherwise.
    max_iterations : int or None
        Bound the solve by this many termination checks (about planner iterations) as well
        as by time; with a seed, replaces the default budget.
    grid_seed : bool
        Sampling planners in R2 and SE2 also get the grid planner's path as a candidate
        (``ompl_solve``): exact wherever the cell graph reaches the goal. False leaves the
        sampling planner on its own (to study it, or for paths that differ with the seed).

    Returns
    -------
    PlanResult

    Raises
    ------
    ValueError
        An argument out of range, naming it (an unknown planner lists those that work).
    PlanError
        START_OUTSIDE_MAP, GOAL_OUTSIDE_MAP, START_OCCUPIED, GOAL_OCCUPIED, before any
        planner runs.
    """
    if not isinstance(field, RiskField):
        raise ValueError(f"field: must be a RiskField, got {type(field).__name__}")
    pspec = planner_spec(planner)
    sspec = space_spec(state_space, field)
    if not is_warm(sspec.name):
        warm_up((sspec.name,))  # before the clock: the compiler's time is not the planner's
    t0 = time.perf_counter()
    args = check_arguments(field, pspec, sspec, start, goal, time_limit, robot_radius, max_risk, risk_weight,
                           allow_unknown, seed, goal_tolerance, turning_radius, max_iterations, grid_seed)

    rules = args.rules
    grid = PackedGrid(field, rules.robot_radius, rules.max_risk, rules.allow_unknown, rules.risk_weight,
                      args.turning_radius)
    check_endpoint(grid, args.start, "start", rules.max_risk)
    check_endpoint(grid, args.goal, "goal", rules.max_risk)
    grid.endpoint_cells = tuple(grid.cell_index(p[: field.ndim]) for p in (args.start, args.goal))  # type: ignore[misc]

    if pspec.make is None:
        return _plan_grid(grid, sspec, args.start, args.goal, t0)
    return plan_ompl(grid, pspec, sspec, args, t0)





def _plan_grid(
    grid: PackedGrid, sspec: SpaceSpec, start: tuple[float, ...], goal: tuple[float, ...], t0: float
) -> PlanResult:
    """The grid planner's path: A* over valid cells, thinned and shortcut where that is never worse."""
    found = grid_path(grid, start, goal)
    points = drop_collinear(found.positions)
    keep = grid.shortcut(points)
    short = points[keep]
    if grid.cost(short) > grid.cost(points) or not grid.evaluate(short).valid:  # never worse, never invalid
        short = points
    path = interpolate_straight(short, grid.resolution)
    if not grid.evaluate(path).valid:  # cannot happen: every cell of every segment was checked
        return plan_result(grid, sspec, GRID, "none", None, None, t0, "grid path failed verification",
                           error_code=NO_VALID_PATH)
    status = "exact" if found.reached else "approximate"
    message = "" if found.reached else "goal unreachable: path to the reachable cell nearest the goal"
    return plan_result(grid, sspec, GRID, status, path, path, t0, message,
                       error_code="" if found.reached else NO_VALID_PATH)

