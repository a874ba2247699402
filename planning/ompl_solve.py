"""Sampling plans with OMPL, the only caller of OMPL's ``solve()``.

A sampling plan, step by step: seed the grid planner's path in the planar spaces; build the
state space, the validity checks and the risk objective; solve; simplify without raising the
cost; keep the cheapest candidate (the planner's path, its simplification, the grid planner's
path, their shortcuts) that verifies cell by cell, interpolated at the map resolution.

Time: the solve stops at OMPL's own timed termination condition (C++, no Python call needed to
fire it) set to leave ``SIMPLIFY_SHARE`` of the limit for simplification and ``_post_reserve``
for verification and interpolation; simplification has its own timed condition.

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

import math
import threading
import time
from typing import Any

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from planning.budget import SEEDED_CLOCK_FACTOR, wall_clock_limit
from planning.checks import Arguments
from planning.grid_search import grid_path
from planning.packed import PackedGrid
from planning.paths import drop_collinear, interpolate_straight, plan_result
from planning.planners import PlannerSpec
from planning.result import NO_VALID_PATH, TIMEOUT, PlanResult
from planning.spaces import OmplSpace, SpaceSpec

ou.setLogLevel(ou.LOG_WARN)  # OMPL logs Info to stdout otherwise

_SOLVE_LOCK = threading.Lock()
SIMPLIFY_SHARE = 0.15  # of time_limit, kept for simplification after an optimizing solve
SEEDED_SIMPLIFY_CHECKS = 20_000  # termination checks a seeded simplification may use
# a seeded solve's default count is this share of what the calibrated rate fits in the solve's
# seconds: headroom so that the count, not the clock, ends it on an unloaded machine
SEEDED_BUDGET_SHARE = 0.6
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


def quiet_ompl(quiet: bool = True) -> None:
    """Let OMPL print errors only (``quiet``), or warnings and errors too (the default at import).

    OMPL writes its messages as plain text on stderr, and its output handler cannot be
    replaced from Python; a service that logs structured lines may want them quiet.
    """
    ou.setLogLevel(ou.LOG_ERROR if quiet else ou.LOG_WARN)


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
    return drop_collinear(found.positions), time.perf_counter() - t0


def plan_ompl(grid: PackedGrid, pspec: PlannerSpec, sspec: SpaceSpec, args: Arguments, t0: float) -> PlanResult:
    """A sampling plan with ``pspec``'s planner on the checked ``args``, its clock started at ``t0``.

    Under the process-wide lock: OMPL's seed is process-global (see the module docstring).
    """
    with _SOLVE_LOCK:
        return _solve(grid, pspec, sspec, args, t0)


def _solve(grid: PackedGrid, pspec: PlannerSpec, sspec: SpaceSpec, args: Arguments, t0: float) -> PlanResult:
    assert pspec.make is not None
    start, goal, seed = args.start, args.goal, args.seed
    time_limit, max_iterations = args.time_limit, args.max_iterations
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

    seed_path, seed_at = _grid_seed(grid, sspec, start, goal, t0, time_limit) if args.grid_seed else (None, None)

    # space, state validity, motion validity, risk objective
    space = sspec.build(grid, args.turning_radius)
    try:
        si = space.si
        # problem: start, goal region, objective (set before the planner's setup, or it is ignored)
        pdef = ob.ProblemDefinition(si)
        pdef.setStartAndGoalStates(space.to_state(start), space.to_state(goal), args.tolerance)
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
            return plan_result(grid, sspec, pspec.name, "none", None, None, t0, "; ".join(notes), iterations,
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
            return plan_result(grid, sspec, pspec.name, "none", None, None, t0, "; ".join(notes), iterations,
                               error_code=NO_VALID_PATH, stopped_by=stopped_by)
        path, fine = best
        return plan_result(grid, sspec, pspec.name, label, path, fine, t0, "; ".join(notes), iterations, first,
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
            dense = interpolate_straight(pts, res)
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
