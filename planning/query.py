"""``plan``: one query, and the only caller of OMPL's ``solve()``.

One query, step by step: check the arguments; pack the field dilated by the robot for the
kernels; refuse an unusable start or goal with Nav2's codes; build the state space, the
validity checks and the risk objective; solve; simplify without raising the cost;
interpolate at the map resolution; verify every crossed cell; measure.

Time: ``time_limit`` bounds the whole call in wall-clock time, seeded or not, except the
one-time compilation of the kernels a state space uses (``warm_up``: seconds on a cold numba
cache, tens of milliseconds from the cache), which the first plan of a process in that space
does before its clock starts: otherwise a first plan would spend its time limit in the
compiler and find nothing. The solve
stops at OMPL's own timed termination condition (C++, no Python call needed to fire it)
set to leave ``SIMPLIFY_SHARE`` of the limit for simplification and ``_post_reserve`` for
verification and interpolation; simplification has its own timed condition.

Reproducibility: OMPL's seed is process-global (``ou.RNG.setSeed``), and every RNG a
planner or simplifier makes draws its own seed from it when constructed. So every plan
constructs, sets up, solves and simplifies under one process-wide lock (``solve()`` holds
the GIL anyway: threads would gain nothing), and a seeded plan seeds first, then ends its
solve by a count of termination checks (about planner iterations): ``max_iterations``, by
default ``SEEDED_BUDGET_SHARE`` x the solve's share of ``time_limit`` x the planner's
calibrated rate (and the state space's factor), which an idle machine finishes well inside
``time_limit``. The clock is only an outer bound for a seeded plan, ``SEEDED_CLOCK_FACTOR`` x
``time_limit`` (:func:`planning.budget.wall_clock_limit`), so a loaded machine that runs the same count
slower still gives the same path; the result's ``stopped_by`` says what ended the solve, and
its message warns when the clock did (the path may then differ between runs).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from planning.budget import SEEDED_CLOCK_FACTOR, wall_clock_limit
from planning.field import DEFAULT_MAX_RISK, RiskField
from planning.grid_search import grid_path
from planning.packed import PackedGrid
from planning.planners import GRID, PlannerSpec, planner_spec
from planning.result import (
    GOAL_OCCUPIED,
    GOAL_OUTSIDE_MAP,
    NO_VALID_PATH,
    START_OCCUPIED,
    START_OUTSIDE_MAP,
    TIMEOUT,
    PlanError,
    PlanResult,
)
from planning.spaces import STATE_SPACES, OmplSpace, SpaceSpec

ou.setLogLevel(ou.LOG_WARN)  # OMPL logs Info to stdout otherwise
log = logging.getLogger(__name__)

_SOLVE_LOCK = threading.Lock()
_WARM_LOCK = threading.RLock()  # re-entered by the warm-up plans' own calls of plan()
_warmed: set[str] = set()  # state spaces whose kernels this process has compiled or loaded
_warming: set[str] = set()  # being warmed up (by the thread holding _WARM_LOCK)
SIMPLIFY_SHARE = 0.15  # of time_limit, kept for simplification after an optimizing solve
SEEDED_SIMPLIFY_CHECKS = 20_000  # termination checks a seeded simplification may use
# a seeded solve's default count is this share of what the calibrated rate fits in the solve's
# seconds: headroom so that the count, not the clock, ends it on an unloaded machine
SEEDED_BUDGET_SHARE = 0.6
#: Bounds a plan's parameters get from its map (``_max_robot_radius``): a robot's dilation may
#: cost at most this many (cell x cell of radius), about 10 s; the risk weight at most this.
MAX_DILATION_WORK = 1e9
MAX_RISK_WEIGHT = 1e4
#: Spaces where a sampling plan is seeded with the grid planner's path (``_grid_seed``); curved
#: motions cannot follow a cell chain, and a 26-connected search of a large 3-D map is not cheap.
GRID_SEEDED_SPACES = ("R2", "SE2")
#: Seconds the grid search spends per expanded cell, at most (measured: 160-240 ns on open maps
#: of 40 k and 2 M cells on a loaded 2-core machine, 250 ns on building maps), and the share of a
#: plan's time limit a grid seed may take (building maps' searches need 40-220 k expansions, a
#: quarter of 1 s buys 830 k): its search stops after that many expansions.
GRID_SEED_S_PER_EXPANSION = 300e-9
GRID_SEED_SHARE = 0.25
CLOCK_NOTE = (f"stopped by the wall-clock bound ({SEEDED_CLOCK_FACTOR:g} x time_limit for a seeded plan) before the "
              "seeded iteration budget; the path may differ between runs")


# ---------------------------------------------------------------- argument checks


def _number(name: str, value: Any, *, low: float, low_open: bool = False, high: float = math.inf) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a number, got {value!r}") from None
    if not math.isfinite(x) or x < low or (low_open and x == low) or x > high:
        bound = f"> {low}" if low_open else f">= {low}"
        if high < math.inf:
            bound += f" and <= {high}"
        raise ValueError(f"{name}: must be a finite number {bound}, got {value!r}")
    return x


def _max_robot_radius(field: RiskField, diagonal: float) -> float:
    """Half the map's diagonal, and no wider than a dilation of ``MAX_DILATION_WORK`` cell-radii.

    The dilation by the robot (``field.py``) costs about the map's cells times the radius in
    cells (1 s for 1 M cells and 100 cells of radius on 2 cores): a radius of a million metres
    asked for petabytes, so the bound is what the map makes sensible, checked before any work.
    """
    cells = max(1, math.prod(field.shape))
    return min(0.5 * diagonal, field.resolution * max(1.0, MAX_DILATION_WORK / cells))


def _point(name: str, value: Any, size: int, space: str) -> tuple[float, ...]:
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


def _space_spec(state_space: str | None, field: RiskField) -> SpaceSpec:
    name = state_space if state_space is not None else ("R3" if field.ndim == 3 else "R2")
    spec = STATE_SPACES.get(name) if isinstance(name, str) else None
    if spec is None:
        raise ValueError(f"state_space: unknown {name!r}; choose one of: {', '.join(STATE_SPACES)}")
    if spec.field_ndim != field.ndim:
        fitting = [s for s, v in STATE_SPACES.items() if v.field_ndim == field.ndim]
        raise ValueError(f"state_space: {name} needs a {spec.field_ndim}-D field, this one is "
                         f"{field.ndim}-D; choose one of: {', '.join(fitting)}")
    return spec


# ---------------------------------------------------------------- start and goal


def _check_endpoint(grid: PackedGrid, point: tuple[float, ...], which: str, max_risk: float) -> None:
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


# ---------------------------------------------------------------- OMPL runs


def _seed(seed: int) -> None:
    # OMPL refuses seed 0 (it uses 1 instead) and logs an error when reseeding: shift the
    # seed by one so every non-negative seed is distinct, and silence the reseed complaint
    level = ou.getLogLevel()
    ou.setLogLevel(ou.LOG_NONE)
    try:
        ou.RNG.setSeed(int(seed) + 1)
    finally:
        ou.setLogLevel(level)


def _post_reserve(time_limit: float) -> float:
    """Seconds kept after simplification for verification, interpolation and measures."""
    return min(0.02 + 0.05 * time_limit, 0.25 * time_limit)


class _Counter:
    """A Python termination condition counting its own checks (never reads the clock).

    It also notes when an optimizing planner first holds a solution (its best cost turns
    finite): OMPL's intermediate-solution callback is not bindable in the 2.0.1 wheel. It is
    evaluated inline by the planner's own thread (no period: a periodic Python condition
    runs in a second thread that deadlocks on the GIL), OR-ed with a timed C++ condition.
    """

    def __init__(self, checks: int | None, t0: float) -> None:
        self.checks = checks
        self.count = 0
        self.t0 = t0
        self.watch: Any = None  # a planner with bestCost()
        self.first_solution: float | None = None

    def __call__(self) -> bool:
        self.count += 1
        if self.first_solution is None and self.watch is not None and math.isfinite(self.watch.bestCost().value()):
            self.first_solution = time.perf_counter() - self.t0
        return self.checks is not None and self.count > self.checks

    @property
    def exhausted(self) -> bool:
        return self.checks is not None and self.count > self.checks


def _until(deadline: float, counter: _Counter | None) -> ob.PlannerTerminationCondition:
    """OMPL's timed condition up to ``deadline`` (perf_counter time), OR-ed with a counter."""
    timed = ob.timedPlannerTerminationCondition(max(0.0, deadline - time.perf_counter()))
    if counter is None:
        return timed
    return ob.plannerOrTerminationCondition(timed, ob.PlannerTerminationCondition(counter))


def _states(space: OmplSpace, path: og.PathGeometric) -> np.ndarray:
    return np.array([space.values(s) for s in path.getStates()], dtype=np.float64)


def _interpolate_ompl(space: OmplSpace, path: og.PathGeometric, step: float) -> np.ndarray:
    """States along the path's own motions (curves for Dubins / Reeds-Shepp), <= step apart."""
    si = space.si
    ss = si.getStateSpace()
    states = path.getStates()
    tmp = si.allocState()  # owned by its Python wrapper: freeing it here would free it twice
    out = [space.values(states[0])]
    for a, b in zip(states[:-1], states[1:], strict=True):
        n = max(1, math.ceil(ss.distance(a, b) / step))
        for k in range(1, n):
            ss.interpolate(a, b, k / n, tmp)
            out.append(space.values(tmp))
        out.append(space.values(b))
    return np.array(out, dtype=np.float64)


def _interpolate_straight(points: np.ndarray, step: float) -> np.ndarray:
    """Points along a polyline no more than ``step`` apart, keeping every vertex (vectorized)."""
    if len(points) < 2:
        return points.copy()
    seg = np.diff(points, axis=0)
    pieces = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / step).astype(np.int64))
    owner = np.repeat(np.arange(len(seg)), pieces)
    starts = np.cumsum(pieces) - pieces
    frac = (np.arange(owner.size) - starts[owner]) / pieces[owner]
    out = points[owner] + frac[:, None] * seg[owner]
    return np.vstack([out, points[-1:]])


def _drop_collinear(points: np.ndarray) -> np.ndarray:
    """Remove interior points where a polyline goes straight on (exact: same segments)."""
    if len(points) < 3:
        return points
    d = np.diff(points, axis=0)
    norms = np.linalg.norm(d, axis=1)
    keep_seg = norms > 0
    points = np.vstack([points[:1], points[1:][keep_seg]])
    if len(points) < 3:
        return points
    d = np.diff(points, axis=0)
    d /= np.linalg.norm(d, axis=1)[:, None]
    turn = np.linalg.norm(d[1:] - d[:-1], axis=1) > 1e-9
    return np.vstack([points[:1], points[1:-1][turn], points[-1:]])


# ---------------------------------------------------------------- the entry point


def plan(
    field: RiskField,
    start: Sequence[float],
    goal: Sequence[float],
    planner: str = "RRTstar",
    state_space: str | None = None,
    time_limit: float = 1.0,
    robot_radius: float = 0.2,
    max_risk: float = DEFAULT_MAX_RISK,
    risk_weight: float = 1.0,
    allow_unknown: bool = True,
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
        ``MAX_DILATION_WORK`` cell-radii allows on this map (``_max_robot_radius``).
    max_risk : float
        In [0, 1]: a position is valid when no observed cell under the footprint has a higher risk
        (never-observed cells are ``allow_unknown``'s). The default, 0.45, is the exports' free
        threshold: the robot drives on cells with net free evidence, or on unknown ones.
    risk_weight : float
        In [0, ``MAX_RISK_WEIGHT``]: cost is ``length + risk_weight * integral of dilated risk`` (metres x risk).
    allow_unknown : bool
        True allows positions whose footprint overlaps never-observed cells (or leaves the map),
        whatever ``max_risk`` says; False forbids them.
    seed : int or None
        In [0, 2**32): seeds OMPL and bounds the solve by iterations (see the module
        docstring) so the same seed gives the same path.
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
        (``_grid_seed``): exact wherever the cell graph reaches the goal. False leaves the
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
    sspec = _space_spec(state_space, field)
    if sspec.name not in _warmed:
        warm_up((sspec.name,))  # before the clock: the compiler's time is not the planner's
    t0 = time.perf_counter()
    if pspec.make is None and sspec.name not in ("R2", "R3"):
        raise ValueError(f"planner: {GRID!r} plans in R2 and R3 only, not in {sspec.name}")
    time_limit = _number("time_limit", time_limit, low=0.0, low_open=True)
    diagonal = math.hypot(*(n * field.resolution for n in field.shape))
    robot_radius = _number("robot_radius", robot_radius, low=0.0, high=_max_robot_radius(field, diagonal))
    max_risk = _number("max_risk", max_risk, low=0.0, high=1.0)
    risk_weight = _number("risk_weight", risk_weight, low=0.0, high=MAX_RISK_WEIGHT)
    tolerance = (
        field.resolution if goal_tolerance is None
        else _number("goal_tolerance", goal_tolerance, low=0.0, low_open=True, high=diagonal)
    )
    if sspec.curved:
        if turning_radius is None:
            raise ValueError(f"turning_radius: required by {sspec.name}")
        # a turning circle wider than the map cannot turn in it (and OMPL's curves lose precision)
        turning_radius = _number("turning_radius", turning_radius, low=0.0, low_open=True, high=diagonal)
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed < 2**32):
        raise ValueError(f"seed: must be an integer in [0, 2**32), got {seed!r}")
    if max_iterations is not None and (
        isinstance(max_iterations, bool) or not isinstance(max_iterations, int | np.integer) or max_iterations < 1
    ):
        raise ValueError(f"max_iterations: must be a positive integer, got {max_iterations!r}")
    if not isinstance(allow_unknown, bool | np.bool_):
        raise ValueError(f"allow_unknown: must be a bool, got {allow_unknown!r}")
    if not isinstance(grid_seed, bool | np.bool_):
        raise ValueError(f"grid_seed: must be a bool, got {grid_seed!r}")
    start_pt = _point("start", start, sspec.state_dim, sspec.name)
    goal_pt = _point("goal", goal, sspec.state_dim, sspec.name)

    grid = PackedGrid(field, robot_radius, max_risk, bool(allow_unknown), risk_weight, turning_radius)
    _check_endpoint(grid, start_pt, "start", max_risk)
    _check_endpoint(grid, goal_pt, "goal", max_risk)
    grid.endpoint_cells = tuple(grid.cell_index(p[: field.ndim]) for p in (start_pt, goal_pt))  # type: ignore[misc]

    if pspec.make is None:
        return _plan_grid(grid, sspec, start_pt, goal_pt, t0)
    with _SOLVE_LOCK:
        return _plan_ompl(
            grid, pspec, sspec, start_pt, goal_pt, t0, time_limit, tolerance, turning_radius, seed, max_iterations,
            bool(grid_seed),
        )


def quiet_ompl(quiet: bool = True) -> None:
    """Let OMPL print errors only (``quiet``), or warnings and errors too (the default at import).

    OMPL writes its messages as plain text on stderr, and its output handler cannot be
    replaced from Python; a service that logs structured lines may want them quiet.
    """
    ou.setLogLevel(ou.LOG_ERROR if quiet else ou.LOG_WARN)


def warm_up(state_spaces: str | Iterable[str] = tuple(STATE_SPACES)) -> float:
    """Compile, or load from numba's on-disk cache, the kernels that plans in these spaces run.

    Plans a small problem (a wall, a risk gradient, an unobserved patch: the compiled
    callbacks' self-check in ``native.py`` runs on it) once per space and process, with the
    grid planner too in R2 and R3; later calls for a space return at once. ``plan`` calls it for
    its own space before its clock starts; a service calls it at startup so that no request
    waits for it. A failed warm-up plan is logged, never raised: the real plan then reports
    what is wrong. Returns the seconds taken.
    """
    started = time.perf_counter()
    names = (state_spaces,) if isinstance(state_spaces, str) else tuple(state_spaces)
    with _WARM_LOCK:  # a second thread waits here until the kernels are ready
        for name in names:
            sspec = STATE_SPACES.get(name)
            if sspec is None:
                raise ValueError(f"state_space: unknown {name!r}; choose one of: {', '.join(STATE_SPACES)}")
            if name in _warmed or name in _warming:
                continue  # done, or being done by this very thread (the warm-up plans call plan())
            _warming.add(name)
            try:
                _warm_space(sspec)
            finally:
                _warming.discard(name)
            _warmed.add(name)
    return time.perf_counter() - started


def _warm_space(sspec: SpaceSpec) -> None:
    rng = np.random.default_rng(0)
    shape = (30, 30) if sspec.field_ndim == 2 else (30, 30, 8)
    risk = rng.uniform(0.0, 0.4, shape).astype(np.float32)
    risk[15, :20] = 1.0  # a wall across x = 1.5 m, open at y >= 2 m
    observed = np.ones(shape, bool)
    observed[24:, 24:] = False
    field = RiskField(risk, 0.1, (0.0,) * len(shape), observed=observed)
    z = [0.4] if sspec.field_ndim == 3 else [0.0]
    start, goal = [0.5, 0.5, *z][: sspec.state_dim], [2.5, 0.5, *z][: sspec.state_dim]
    planners = [GRID, "RRTConnect"] if sspec.name in ("R2", "R3") else ["RRTConnect"]
    for planner in planners:
        for allow_unknown in (True, False):
            try:
                # unseeded: OMPL's seed is process-wide, and a warm-up must not fix the RNG of the
                # process's later unseeded plans
                plan(field, start, goal, planner=planner, state_space=sspec.name, time_limit=10.0,
                     robot_radius=0.1, allow_unknown=allow_unknown,
                     turning_radius=0.3 if sspec.curved else None)
            except Exception:  # noqa: BLE001 - reported by the real plan, not here
                log.warning("warm-up plan in %s with %s failed", sspec.name, planner, exc_info=True)


def _result(
    grid: PackedGrid,
    sspec: SpaceSpec,
    planner: str,
    status: str,
    path: np.ndarray | None,
    measure_points: np.ndarray | None,
    t0: float,
    message: str = "",
    iterations: int = 0,
    first_solution_time: float | None = None,
    error_code: str = "",
    stopped_by: str = "complete",
) -> PlanResult:
    if status == "none" or path is None or measure_points is None:
        nan = math.nan
        empty = np.zeros((0, sspec.state_dim))
        return PlanResult("none", empty, nan, nan, nan, nan, planner, sspec.name,
                          time.perf_counter() - t0, message, iterations, nan, error_code, stopped_by)  # fmt: skip
    m = grid.evaluate(measure_points[:, : grid.ndim])
    elapsed = time.perf_counter() - t0
    if m.length > 0:
        mean = m.integral / m.length
    else:
        mean = m.peak
    return PlanResult(
        status,  # type: ignore[arg-type]
        path,
        m.length,
        m.peak,
        mean,
        m.length + grid.risk_weight * m.integral,
        planner,
        sspec.name,
        elapsed,
        message,
        iterations,
        first_solution_time if first_solution_time is not None else elapsed,
        error_code,
        stopped_by,  # type: ignore[arg-type]
    )


def _plan_grid(
    grid: PackedGrid, sspec: SpaceSpec, start: tuple[float, ...], goal: tuple[float, ...], t0: float
) -> PlanResult:
    found = grid_path(grid, start, goal)
    points = _drop_collinear(found.positions)
    keep = grid.shortcut(points)
    short = points[keep]
    if grid.cost(short) > grid.cost(points) or not grid.evaluate(short).valid:  # never worse, never invalid
        short = points
    path = _interpolate_straight(short, grid.resolution)
    if not grid.evaluate(path).valid:  # cannot happen: every cell of every segment was checked
        return _result(grid, sspec, GRID, "none", None, None, t0, "grid path failed verification",
                       error_code=NO_VALID_PATH)
    status = "exact" if found.reached else "approximate"
    message = "" if found.reached else "goal unreachable: path to the reachable cell nearest the goal"
    return _result(grid, sspec, GRID, status, path, path, t0, message,
                   error_code="" if found.reached else NO_VALID_PATH)


def _grid_seed(
    grid: PackedGrid, sspec: SpaceSpec, start: tuple[float, ...], goal: tuple[float, ...], t0: float,
    time_limit: float,
) -> tuple[np.ndarray | None, float | None]:
    """The grid planner's path from start to goal for a sampling planner, and when it was found.

    In the planar spaces with straight motions (``GRID_SEEDED_SPACES``) a sampling plan first
    runs the grid search (tens of milliseconds on a building's map): its path is a candidate
    beside the sampling planner's, so a plan is exact wherever the cell graph reaches the goal,
    and the cheaper verified path wins. The search reads no clock, so it is bounded by a count
    of expansions worth ``GRID_SEED_SHARE`` of the time limit (a count, not the clock: a seeded
    plan gets the same seed on a loaded machine). (None, None) in other spaces, or when the
    goal is unreachable or not reached within that count.
    """
    if sspec.name not in GRID_SEEDED_SPACES:
        return None, None
    budget = int(GRID_SEED_SHARE * time_limit / GRID_SEED_S_PER_EXPANSION)
    found = grid_path(grid, start[: grid.ndim], goal[: grid.ndim], max_expansions=budget)
    if not found.reached:
        return None, None
    return _drop_collinear(found.positions), time.perf_counter() - t0


def _plan_ompl(
    grid: PackedGrid,
    pspec: PlannerSpec,
    sspec: SpaceSpec,
    start: tuple[float, ...],
    goal: tuple[float, ...],
    t0: float,
    time_limit: float,
    tolerance: float,
    turning_radius: float | None,
    seed: int | None,
    max_iterations: int | None,
    grid_seed: bool,
) -> PlanResult:
    assert pspec.make is not None
    notes: list[str] = []
    # the seed comes before anything that constructs an RNG (spaces, samplers, planners)
    if seed is not None:
        _seed(seed)
    clock = wall_clock_limit(time_limit, seed is not None)
    end = t0 + clock
    post = _post_reserve(clock)
    solve_end = end - post - SIMPLIFY_SHARE * clock
    if seed is not None:
        if max_iterations is not None:
            checks = max_iterations
        else:
            seconds = max(0.0, (1.0 - SIMPLIFY_SHARE) * time_limit - _post_reserve(time_limit))  # the nominal solve
            checks = max(1, round(SEEDED_BUDGET_SHARE * seconds * pspec.rate * sspec.rate_factor))
        counter = _Counter(checks, t0)
    else:
        counter = _Counter(max_iterations, t0)

    seed_path, seed_at = _grid_seed(grid, sspec, start, goal, t0, time_limit) if grid_seed else (None, None)

    # space, state validity, motion validity, risk objective
    space = sspec.build(grid, turning_radius)
    try:
        si = space.si
        # problem: start, goal region, objective (set before the planner's setup, or it is ignored)
        pdef = ob.ProblemDefinition(si)
        pdef.setStartAndGoalStates(space.to_state(start), space.to_state(goal), tolerance)
        objective = space.objective
        pdef.setOptimizationObjective(objective)
        # planner, then solve
        planner = pspec.make(si)
        planner.setProblemDefinition(pdef)
        planner.setup()
        watching = pspec.optimizing and hasattr(planner, "bestCost")
        if watching:
            counter.watch = planner
        use_counter = watching or counter.checks is not None
        status = planner.solve(_until(solve_end, counter if use_counter else None))
        solved_at = time.perf_counter() - t0
        iterations = int(planner.numIterations()) if hasattr(planner, "numIterations") else 0
        kind = status.getStatus()
        finished = kind == ob.PlannerStatus.EXACT_SOLUTION and not pspec.optimizing  # stopped at its first solution
        stopped_by = "solution" if finished else "iterations" if counter.exhausted else "time_limit"
        if seed is not None and stopped_by == "time_limit" and time.perf_counter() >= solve_end:
            notes.append(CLOCK_NOTE)
        own_exact = kind == ob.PlannerStatus.EXACT_SOLUTION and pdef.hasExactSolution()
        if own_exact:
            label = "exact"
        elif seed_path is not None:
            label = "exact"
            notes.append(f"{pspec.name} reached no exact path in its budget: the path is the grid planner's seed")
        elif kind in (ob.PlannerStatus.EXACT_SOLUTION, ob.PlannerStatus.APPROXIMATE_SOLUTION) and pdef.hasSolution():
            label = "approximate"
            unit = " m" if sspec.name in ("R2", "R3") else " (in the state space's distance)"
            notes.append(f"goal not reached: the path ends {pdef.getSolutionDifference():.3g}{unit} from the goal region")
        else:
            notes.append(f"no path found ({status.asString()})")
            code = TIMEOUT if kind == ob.PlannerStatus.TIMEOUT else NO_VALID_PATH
            return _result(grid, sspec, pspec.name, "none", None, None, t0, "; ".join(notes), iterations,
                           error_code=code, stopped_by=stopped_by)
        first = counter.first_solution if counter.first_solution is not None else solved_at
        if seed_at is not None:
            first = min(first, seed_at) if own_exact else seed_at

        candidates: list[og.PathGeometric] = []
        if own_exact or seed_path is None:
            # simplify with the risk objective; keep whichever candidate is cheapest and verifies
            raw = og.PathGeometric(pdef.getSolutionPath())  # a copy: the simplifier edits in place
            simplified = og.PathGeometric(raw)
            simp_counter = _Counter(SEEDED_SIMPLIFY_CHECKS, t0) if seed is not None else None
            simp_end = end - post
            og.PathSimplifier(si, pdef.getGoal(), objective).simplify(simplified, _until(simp_end, simp_counter))
            if (
                simp_counter is not None
                and not simp_counter.exhausted
                and time.perf_counter() >= simp_end
                and CLOCK_NOTE not in notes
            ):
                notes.append("simplification " + CLOCK_NOTE)
            candidates = [simplified, raw]
        seeds = [] if seed_path is None else [seed_path]
        best = _pick(grid, space, sspec, candidates, pdef if label == "exact" else None, goal, start, seeds)
        if best is None:
            notes.append("every candidate path crossed an invalid cell between the planner's checks")
            return _result(grid, sspec, pspec.name, "none", None, None, t0, "; ".join(notes), iterations,
                           error_code=NO_VALID_PATH, stopped_by=stopped_by)
        path, fine = best
        return _result(grid, sspec, pspec.name, label, path, fine, t0, "; ".join(notes), iterations, first,
                       error_code="" if label == "exact" else TIMEOUT, stopped_by=stopped_by)
    finally:
        space.close()  # the compiled objective's table goes back to its pool


def _pick(
    grid: PackedGrid,
    space: OmplSpace,
    sspec: SpaceSpec,
    candidates: list[og.PathGeometric],
    exact_pdef: ob.ProblemDefinition | None,
    goal: tuple[float, ...],
    start: tuple[float, ...],
    seeds: list[np.ndarray],
) -> tuple[np.ndarray, np.ndarray] | None:
    """The cheapest candidate that verifies, as (path at the resolution, verified polyline).

    Straight-motion spaces also try the deterministic shortcut of each candidate and of each
    of ``seeds`` (polylines of positions from start to goal, the grid planner's), and an
    exact path that stops inside the goal tolerance is extended to the goal itself when that
    last straight piece is valid. Curved motions are verified as chords a quarter cell long
    (each strays from its arc by at most res^2 / (128 r)); the path returned is the same
    curve sampled every cell.
    """
    res = grid.resolution
    options: list[tuple[float, np.ndarray, np.ndarray]] = []
    se2 = sspec.name == "SE2"
    polylines: list[tuple[np.ndarray, float, float]] = [  # positions, start and end heading (SE2 only)
        (seed[:, : grid.ndim], start[2] if se2 else 0.0, goal[2] if se2 else 0.0) for seed in seeds
    ]
    for path in candidates:
        if exact_pdef is not None and not exact_pdef.getGoal().isSatisfied(path.getState(path.getStateCount() - 1)):
            continue  # an approximate path never passes as exact
        if sspec.curved:
            fine = _interpolate_ompl(space, path, 0.25 * res)
            coarse = _interpolate_ompl(space, path, res)
            # the curve is verified as quarter-cell chords; the path handed out samples it
            # every cell, unless its own chords clip a cell the curve does not
            m = grid.evaluate(fine[:, :2])
            if m.valid:
                options.append((m.length + grid.risk_weight * m.integral,
                                coarse if grid.evaluate(coarse[:, :2]).valid else fine, fine))
            continue
        vertices = _states(space, path)
        positions = vertices[:, : grid.ndim]
        if exact_pdef is not None:
            target = np.asarray(goal[: grid.ndim])
            if np.any(positions[-1] != target) and grid.evaluate(np.vstack([positions[-1], target])).valid:
                positions = np.vstack([positions, target])
        if se2:
            polylines.append((positions, vertices[0, 2], goal[2] if exact_pdef is not None else vertices[-1, 2]))
        else:
            polylines.append((positions, 0.0, 0.0))
    for positions, yaw0, yaw1 in polylines:
        for pts in (positions[grid.shortcut(positions)], positions):
            dense = _interpolate_straight(pts, res)
            if se2:
                # heading is free in plain SE2 (position-only cost, footprint a disk): turn
                # steadily from the start's heading to the goal's (or the last state's)
                dense = np.column_stack([dense, _steady_heading(dense, yaw0, yaw1)])
            m = grid.evaluate(dense[:, : grid.ndim])
            if m.valid:
                options.append((m.length + grid.risk_weight * m.integral, dense, dense))
    if not options:
        return None
    options.sort(key=lambda o: o[0])
    return options[0][1], options[0][2]


def _steady_heading(points: np.ndarray, yaw0: float, yaw1: float) -> np.ndarray:
    """Headings turning at a constant rate per metre from yaw0 to yaw1 (the shorter way)."""
    step = np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(step)])
    frac = s / s[-1] if s[-1] > 0 else np.linspace(0.0, 1.0, len(points))
    turn = math.remainder(yaw1 - yaw0, 2.0 * math.pi)
    return np.remainder(yaw0 + turn * frac + math.pi, 2.0 * math.pi) - math.pi
