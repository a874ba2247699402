"""Planner success, speed and path quality on fixed, seeded risk maps, against the grid optimum.

    python -m bench.bench_planning [--quick] [--seed N] [--runs R] [--time-limit S]
                                                            (from the repository root)

Three 400 x 400 maps at 0.05 m (20 m x 20 m), generated from a fixed seed:

- rooms: 4 x 4 rooms with 3-cell walls and 1 m doors, furniture boxes, and a soft risk halo
  (<= 0.4, passable) around every obstacle, as a fuzzy map draws them;
- maze: a 10 x 10 maze of 2 m cells with one-cell walls (sampling planners cut such corners);
- risky: an open floor with a few boxes and two broad high-risk but passable regions (risk up
  to 0.55 < max_risk) across the straight line, so the best path trades length for risk.

Every planner plans (robot_radius 0.2 m, max_risk 0.6, risk_weight 1) from (1, 1) to (19, 19)
``runs`` times, time-bounded (``time_limit``, 1 s by default). Per planner and map it prints the
success rate (exact, verified paths), the median time to the first solution, and the median
cost after ``time_limit`` divided by the grid planner's cost on the same map (the grid planner
is A* over the 8-connected cell graph, then shortcut; its cost is the yardstick). Every returned
path is re-checked independently: points every quarter cell, the worst raw-risk cell under the
robot's disk at each point, which must not exceed max_risk (a count of violations is printed).

Last, RRTstar's iterations per CPU second with the risk objective against OMPL's built-in C++
path-length objective, the same planner configuration and seeds: over a fixed iteration count
(both build the same vertices) and over equal time (the target: ratio >= 0.5). The risk objective
is measured as ``plan`` uses it (compiled into OMPL, ``planning/native.py``) and as the Python
subclass it falls back to; a plain-Python length objective shows the floor any Python objective
pays; and the number and rate of motionCost calls.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from dataclasses import dataclass

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou
from scipy import ndimage

from planning import RiskField, available_planners, native, plan
from planning.packed import PackedGrid
from planning.planners import PLANNERS
from planning.spaces import STATE_SPACES

RES = 0.05
N = 400
ROBOT_RADIUS = 0.2
MAX_RISK = 0.6
RISK_WEIGHT = 1.0
START = (1.0, 1.0)
GOAL = (19.0, 19.0)
QUICK_PLANNERS = ("RRTConnect", "RRTstar", "InformedRRTstar", "BITstar")


@dataclass
class BenchMap:
    name: str
    field: RiskField


# ---------------------------------------------------------------- maps


def _halo(obstacles: np.ndarray, peak: float, sigma_m: float) -> np.ndarray:
    """Obstacles at risk 1 with a soft, passable halo around them."""
    d = ndimage.distance_transform_edt(~obstacles) * RES
    risk = peak * np.exp(-0.5 * (d / sigma_m) ** 2)
    risk[obstacles] = 1.0
    return risk.astype(np.float32)


def _clear(mask: np.ndarray, point: tuple[float, float], radius_m: float) -> None:
    i, j = int(point[0] / RES), int(point[1] / RES)
    r = int(radius_m / RES)
    mask[max(i - r, 0) : i + r + 1, max(j - r, 0) : j + r + 1] = False


def rooms(rng: np.random.Generator) -> BenchMap:
    occ = np.zeros((N, N), dtype=bool)
    occ[:3, :] = occ[-3:, :] = occ[:, :3] = occ[:, -3:] = True
    room = N // 4
    door = 20
    for k in range(1, 4):
        c = k * room
        occ[c - 1 : c + 2, :] = True  # wall along y at x = c
        occ[:, c - 1 : c + 2] = True
    for k in range(1, 4):  # one door per wall segment between two rooms
        c = k * room
        for seg in range(4):
            lo = seg * room + 8
            a = int(rng.integers(lo, lo + room - 16 - door))
            occ[c - 1 : c + 2, a : a + door] = False
            b = int(rng.integers(lo, lo + room - 16 - door))
            occ[b : b + door, c - 1 : c + 2] = False
    for _ in range(40):  # furniture
        w, h = rng.integers(6, 24, 2)
        i, j = rng.integers(6, N - 30, 2)
        occ[i : i + w, j : j + h] = True
    _clear(occ, START, 0.6)
    _clear(occ, GOAL, 0.6)
    occ[:3, :] = occ[-3:, :] = occ[:, :3] = occ[:, -3:] = True
    return BenchMap("rooms", RiskField(_halo(occ, 0.4, 0.15), RES, (0.0, 0.0)))


def maze(rng: np.random.Generator, cells: int = 10) -> BenchMap:
    """Randomized depth-first maze, one-cell walls on the maze-cell borders."""
    size = N // cells
    occ = np.zeros((N, N), dtype=bool)
    occ[::size, :] = True
    occ[:, ::size] = True
    occ[-1, :] = occ[:, -1] = True
    seen = np.zeros((cells, cells), dtype=bool)
    stack = [(0, 0)]
    seen[0, 0] = True
    while stack:
        ci, cj = stack[-1]
        options = [
            (ci + di, cj + dj)
            for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= ci + di < cells and 0 <= cj + dj < cells and not seen[ci + di, cj + dj]
        ]
        if not options:
            stack.pop()
            continue
        ni, nj = options[int(rng.integers(len(options)))]
        seen[ni, nj] = True
        if ni != ci:  # open the wall between the two maze cells (keep its ends)
            x = max(ni, ci) * size
            occ[x, cj * size + 1 : (cj + 1) * size] = False
        else:
            y = max(nj, cj) * size
            occ[ci * size + 1 : (ci + 1) * size, y] = False
        stack.append((ni, nj))
    risk = occ.astype(np.float32)
    return BenchMap("maze", RiskField(risk, RES, (0.0, 0.0)))


def risky(rng: np.random.Generator) -> BenchMap:
    occ = np.zeros((N, N), dtype=bool)
    for _ in range(12):
        w, h = rng.integers(8, 30, 2)
        i, j = rng.integers(40, N - 60, 2)
        occ[i : i + w, j : j + h] = True
    _clear(occ, START, 0.6)
    _clear(occ, GOAL, 0.6)
    risk = _halo(occ, 0.3, 0.1)
    x = (np.arange(N) + 0.5) * RES
    xx, yy = np.meshgrid(x, x, indexing="ij")
    for cx, cy, s in ((7.0, 8.0, 2.5), (13.0, 12.5, 2.0)):
        blob = 0.55 * np.exp(-0.5 * ((xx - cx) ** 2 + (yy - cy) ** 2) / s**2)
        risk = np.maximum(risk, blob.astype(np.float32))
    return BenchMap("risky", RiskField(risk, RES, (0.0, 0.0)))


# ---------------------------------------------------------------- independent check


def footprint_violations(field: RiskField, path: np.ndarray, radius: float, limit: float) -> int:
    """Points (every quarter cell along the path) where the raw risk under the disk exceeds limit.

    Independent of the planner's dilation: for each point, every cell whose square the
    open disk overlaps is looked at directly.
    """
    if len(path) == 0:
        return 0
    pts = path[:, :2]
    seg = np.diff(pts, axis=0)
    n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / (0.25 * field.resolution))).astype(int)
    dense = [pts[:1]]
    for a, d, k in zip(pts[:-1], seg, n, strict=True):
        dense.append(a + d * (np.arange(1, k + 1) / k)[:, None])
    dense_pts = np.concatenate(dense)
    res = field.resolution
    m = int(math.ceil(radius / res)) + 1
    off = np.arange(-m, m + 1)
    oi, oj = np.meshgrid(off, off, indexing="ij")
    u = (dense_pts - np.asarray(field.origin)) / res
    base = np.floor(u).astype(int)
    ci = base[:, 0, None] + oi.ravel()[None]
    cj = base[:, 1, None] + oj.ravel()[None]
    # distance from the point to each cell's square
    dx = np.maximum(np.maximum(ci - u[:, 0, None], u[:, 0, None] - (ci + 1)), 0.0) * res
    dy = np.maximum(np.maximum(cj - u[:, 1, None], u[:, 1, None] - (cj + 1)), 0.0) * res
    under = (dx * dx + dy * dy < radius * radius) | ((ci == base[:, 0, None]) & (cj == base[:, 1, None]))
    nx, ny = field.shape
    inside = (ci >= 0) & (ci < nx) & (cj >= 0) & (cj < ny)
    risk = np.where(inside, field.risk[np.clip(ci, 0, nx - 1), np.clip(cj, 0, ny - 1)], 0.5)
    worst = np.where(under, risk, 0.0).max(axis=1)
    return int((worst > limit).sum())


# ---------------------------------------------------------------- runs


def run_planners(maps: list[BenchMap], planners: list[str], runs: int, time_limit: float) -> None:
    violations = 0
    header = f"{'map':7s} {'planner':16s} {'success':>8s} {'first sol (ms)':>15s} {'cost / grid':>12s} {'cost':>8s}"
    print(header)
    print("-" * len(header))
    best_ratio: dict[str, tuple[float, str]] = {}
    firsts_all: dict[str, list[float]] = {}
    worst_time = 0.0
    for bm in maps:
        ref = plan(bm.field, START, GOAL, planner="grid", robot_radius=ROBOT_RADIUS, max_risk=MAX_RISK,
                   risk_weight=RISK_WEIGHT)  # fmt: skip
        assert ref.status == "exact", ref.message
        violations += footprint_violations(bm.field, ref.path, ROBOT_RADIUS, MAX_RISK)
        print(f"{bm.name:7s} {'grid':16s} {'1/1':>8s} {1000 * ref.planning_time:15.1f} {1.0:12.3f} {ref.cost:8.2f}")
        for name in planners:
            ok, firsts, ratios = 0, [], []
            for _ in range(runs):
                res = plan(bm.field, START, GOAL, planner=name, time_limit=time_limit, robot_radius=ROBOT_RADIUS,
                           max_risk=MAX_RISK, risk_weight=RISK_WEIGHT)  # fmt: skip
                violations += footprint_violations(bm.field, res.path, ROBOT_RADIUS, MAX_RISK)
                worst_time = max(worst_time, res.planning_time)
                if res.status == "exact":
                    ok += 1
                    firsts.append(res.first_solution_time)
                    ratios.append(res.cost / ref.cost)
            firsts_all.setdefault(name, []).extend(firsts)
            first = 1000 * statistics.median(firsts) if firsts else math.nan
            ratio = statistics.median(ratios) if ratios else math.nan
            if PLANNERS[name].optimizing and ratios and ratio < best_ratio.get(bm.name, (math.inf, ""))[0]:
                best_ratio[bm.name] = (ratio, name)
            print(f"{bm.name:7s} {name:16s} {f'{ok}/{runs}':>8s} {first:15.1f} {ratio:12.3f} "
                  f"{ratio * ref.cost:8.2f}")  # fmt: skip
        print()
    print("targets:")
    if "RRTConnect" in firsts_all and firsts_all["RRTConnect"]:
        med = 1000 * statistics.median(firsts_all["RRTConnect"])
        print(f"  RRTConnect median time to first solution, all maps and runs: {med:.1f} ms (target < 50 ms)")
    print("  best optimizing planner, median cost / grid after the time limit (target <= 1.10): "
          + ", ".join(f"{k} {v:.3f} ({n})" for k, (v, n) in best_ratio.items()))  # fmt: skip
    print(f"  longest planning_time of any plan: {1000 * worst_time:.0f} ms "
          f"(target <= time_limit + 100 ms = {1000 * time_limit + 100:.0f} ms)")  # fmt: skip
    print(f"  returned paths violating max_risk under the footprint, independent dense check: {violations} (target 0)")


class _Counting(ob.PathLengthOptimizationObjective):
    """Wraps the risk objective to count motionCost calls."""

    def __init__(self, si: ob.SpaceInformation, inner: ob.OptimizationObjective) -> None:
        super().__init__(si)
        self.inner = inner
        self.calls = 0

    def motionCost(self, s1: object, s2: object) -> ob.Cost:  # noqa: N802
        self.calls += 1
        return self.inner.motionCost(s1, s2)


class _PythonLength(ob.PathLengthOptimizationObjective):
    """The cheapest objective Python can offer: the length, in plain Python (a reference)."""

    def motionCost(self, s1: object, s2: object) -> ob.Cost:  # noqa: N802
        dx = s1[0] - s2[0]  # type: ignore[index]
        dy = s1[1] - s2[1]  # type: ignore[index]
        return ob.Cost(math.sqrt(dx * dx + dy * dy))


def _rrtstar_run(field: RiskField, objective: str, seed: int, *, iterations: int = 0, seconds: float = 0.0):
    """RRTstar as ``plan`` configures it, seeded; iterations per CPU second and motionCost calls."""
    grid = PackedGrid(field, ROBOT_RADIUS, MAX_RISK, True, RISK_WEIGHT)
    level = ou.getLogLevel()
    ou.setLogLevel(ou.LOG_NONE)
    ou.RNG.setSeed(seed)
    ou.setLogLevel(level)
    native.set_enabled(objective != "python-risk")
    try:
        space = STATE_SPACES["R2"].build(grid, None)
    finally:
        native.set_enabled(True)
    if objective in ("risk", "count") and space.native is None:
        raise SystemExit(f"the compiled risk objective is off: {native.status()}")
    pdef = ob.ProblemDefinition(space.si)
    pdef.setStartAndGoalStates(space.to_state(START), space.to_state(GOAL), RES)
    counter = None
    obj: ob.OptimizationObjective
    if objective == "length":
        obj = ob.PathLengthOptimizationObjective(space.si)
    elif objective == "python-length":
        obj = _PythonLength(space.si)
    elif objective in ("risk", "python-risk"):
        obj = space.objective
    else:
        obj = counter = _Counting(space.si, space.objective)
    pdef.setOptimizationObjective(obj)
    planner = PLANNERS["RRTstar"].make(space.si)  # type: ignore[misc]
    planner.setProblemDefinition(pdef)
    planner.setup()
    t0 = time.process_time()
    if iterations:
        ptc = ob.PlannerTerminationCondition(lambda: planner.numIterations() >= iterations)
    else:
        ptc = ob.PlannerTerminationCondition(lambda: time.process_time() - t0 >= seconds)
    planner.solve(ptc)
    dt = time.process_time() - t0
    space.close()
    return planner.numIterations() / dt, (counter.calls if counter else 0), planner.numIterations()


def objective_overhead(field: RiskField, iterations: int, seconds: float, repeats: int) -> None:
    """RRTstar iterations/s: risk objective against the built-in C++ length objective (target >= 0.5)."""
    seeds = [7 + r for r in range(repeats)]
    names = ("length", "risk", "python-risk", "python-length")
    for label, kw in ((f"{iterations} iterations each (same vertices)", {"iterations": iterations}),
                      (f"{seconds:g} s each", {"seconds": seconds})):  # fmt: skip
        runs: dict[str, list[float]] = {name: [] for name in names}
        for s in seeds:  # interleaved, so that other work on the machine hits every objective alike
            for name in names:
                runs[name].append(_rrtstar_run(field, name, s, **kw)[0])
        rates = {name: statistics.median(r) for name, r in runs.items()}
        print(f"RRTstar, rooms map, {label}:")
        for name, text in (("length", "built-in C++ length objective"),
                           ("risk", "risk objective as plan() uses it (compiled)"),
                           ("python-risk", "risk objective in Python (the fallback)"),
                           ("python-length", "plain-Python length (any Python objective's floor)")):  # fmt: skip
            print(f"  {text:52s} {rates[name]:8.0f} it/s   ratio {rates[name] / rates['length']:.2f}")
    rate, calls, done = _rrtstar_run(field, "count", seeds[0], iterations=iterations)
    print(f"risk objective: {calls / done:.1f} motionCost calls per iteration")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer runs and planners")
    parser.add_argument("--seed", type=int, default=2024, help="map generator seed")
    parser.add_argument("--runs", type=int, default=None, help="runs per planner and map")
    parser.add_argument("--time-limit", type=float, default=1.0, help="seconds per plan")
    args = parser.parse_args()
    runs = args.runs or (2 if args.quick else 5)
    planners = list(QUICK_PLANNERS) if args.quick else [p for p in available_planners() if p != "grid"]
    rng = np.random.default_rng(args.seed)
    maps = [rooms(rng), maze(rng), risky(rng)]
    # compile and load every kernel before timing anything
    plan(maps[0].field, START, GOAL, planner="RRTConnect", robot_radius=ROBOT_RADIUS)
    print(f"maps {N} x {N} at {RES} m, robot_radius {ROBOT_RADIUS}, max_risk {MAX_RISK}, risk_weight {RISK_WEIGHT}, "
          f"time_limit {args.time_limit} s, {runs} runs per planner\n")  # fmt: skip
    run_planners(maps, planners, runs, args.time_limit)
    print()
    objective_overhead(maps[0].field, 3000 if args.quick else 10000, 0.5 if args.quick else 1.0, 1 if args.quick else 3)


if __name__ == "__main__":
    main()
