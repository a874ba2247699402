"""Planner success, speed and path quality on fixed, seeded risk maps, against the grid optimum.

    python -m bench.bench_planning [--quick] [--seed N] [--runs R] [--time-limit S]
                                   [--real-only | --synthetic-only] [--logs a,b] [--pairs N]
                                   [--planners a,b] [--repeats N] [--no-http]
                                                            (from the repository root)

Two sections: the synthetic maps below, then maps of real buildings (at the end).

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

Real maps (``bench/_real_plans.py``): a map per CARMEN log of the data directory
(``--data DIR``, ``bench/_data.py``; ``--logs``, default
belgioioso, csail and orebro: 1.4-2.0 M cells of 0.05 m), every scan fused with the default engine;
``--pairs`` queries between far-apart poses the robot drove (``_plan_audit.pick_pairs``). Printed:
per planner (grid and the sampling planners a user would pick, 1 s, seeded with the pair's number)
the exact rate, time to first solution, cost / the grid planner's, least clearance to our map's
cells at risk >= 0.6; our grid search beside pyastar2d and scikit-image's ``route_through_array`` on
the same cost grid (best of ``--repeats``); the same queries over HTTP (``python -m app`` on a free
port, the map built there by ``app.import_log --url``) beside the same ``plan`` in-process; and the
issue's targets as met / NOT met.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import dataclass

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou
from scipy import ndimage

from bench import _data, _real_plans
from planning import RiskField, available_planners, native, plan, warm_up
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


# ---------------------------------------------------------------- real maps


def _md(headers: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _ms(seconds: float) -> str:
    return "-" if not math.isfinite(seconds) else f"{1000 * seconds:.1f}"


def _frac(k: int, n: int) -> str:
    return f"{k}/{n} ({100 * k / n:.0f} %)" if n else "-"


def _planner_row(runs: list, label: str, clear_min: float, time_limit: float) -> list[str]:
    mine = [r for r in runs if r.label == label]
    exact = [r for r in mine if r.exact]
    firsts = [r.first_s for r in exact]
    times = [r.plan_s for r in mine]
    ratios = _real_plans.cost_ratios(runs, label)
    grid = _real_plans.grid_costs(runs)
    took = sum(r.took_grid_path(grid.get((r.log, r.pair), math.nan)) for r in mine) if label != "grid" else None
    clears = [r.clearance for r in mine if math.isfinite(r.clearance)]
    close = sum(c < clear_min - 1e-9 for c in clears)
    ratio = (f"{statistics.median(ratios):.3f} ({min(ratios):.3f}-{max(ratios):.3f})" if ratios else "-")
    return [label, _frac(len(exact), len(mine)), f"{sum(r.in_time(time_limit) for r in mine)}/{len(mine)}",
            "-" if took is None else f"{took}/{len(mine)}",
            f"{_ms(_real_plans.p50(firsts))} ({_ms(max(firsts) if firsts else math.nan)})",
            f"{_ms(_real_plans.p50(times))} ({_ms(max(times) if times else math.nan)})",
            ratio, f"{min(clears):.2f}" if clears else "-", f"{close}/{len(clears)}"]


def _notes(runs: list, label: str) -> list[str]:
    """The distinct non-empty messages of a planner's plans with their counts (what a plan said about itself)."""
    counts: dict[str, int] = {}
    for r in runs:
        if r.label == label and r.message:
            counts[r.message] = counts.get(r.message, 0) + 1
    return [f"  {label}: {n} x {msg!r}" for msg, n in sorted(counts.items(), key=lambda kv: -kv[1])]


def real_maps(logs: list[str], pairs: int, planners: list[str], time_limit: float, repeats: int,
              http: bool, alone: bool = True) -> None:
    """The real-map section: planners, grid search baselines and HTTP on maps of the recorded logs (``--data``)."""
    import datetime
    import os
    import platform

    print("## Real maps\n")
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    try:
        from bench._client import machine
        where = machine()
    except ImportError:  # psutil missing: the bench extra is not installed
        where = f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}"
    compiled = ", ".join(f"{k}: {v}" for k, v in sorted(native.status().items()) if k.endswith(" R2"))
    print(f"{now}; {where}; Python {platform.python_version()}; OMPL callbacks in R2: {compiled or '?'}")
    version = _real_plans.code_version()
    print(f"command: {' '.join(sys.argv)}; code: {version}")
    clear_min = ROBOT_RADIUS - _real_plans._logmaps.RESOLUTION
    maps = []
    for name in logs:
        t0 = time.perf_counter()
        rm = _real_plans.build_map(_real_plans.log_path(name), pairs)
        aparts = [q.apart for q in rm.queries]
        print(f"map {rm.name}: {rm.scans} scans (all) fused in {rm.fuse_s:.1f} s, {rm.spec.shape[0]} x "
              f"{rm.spec.shape[1]} = {rm.cells / 1e6:.2f} M cells of {rm.spec.resolution} m; {len(rm.queries)} "
              f"queries {min(aparts):.0f}-{max(aparts):.0f} m apart (built in {time.perf_counter() - t0:.1f} s)",
              flush=True)
        maps.append(rm)
    print(f"planners: grid and {', '.join(planners)}; time_limit {time_limit:g} s, seeded with the pair's number "
          f"(plan's default seeded budget); robot_radius {ROBOT_RADIUS} m, max_risk {MAX_RISK}, risk_weight "
          f"{RISK_WEIGHT}; clearance = least distance from the path's cells to our map's cells at risk >= "
          f"{_real_plans.OCCUPIED} (centre to centre), too close: < radius - 1 cell = {clear_min:.2f} m\n",
          flush=True)

    # every planner on every query
    runs: list = []
    alone = alone and _real_plans.can_plan_alone()
    for rm in maps:
        t0 = time.perf_counter()
        runs += _real_plans.run_planners(rm, planners, time_limit, alone=alone)
        print(f"bench planning: {rm.name}: {len(rm.queries)} queries x {len(planners) + 1} planners"
              f"{' (the sampling ones also alone)' if alone else ''} in {time.perf_counter() - t0:.0f} s", flush=True)
    order = ["grid", *planners, *([f"{p} (alone)" for p in planners] if alone else [])]
    print("\n### Planners on real maps, all logs\n")
    print(f"(alone) = the same planner with grid_seed=False: plan() seeds a sampling planner with the grid planner's "
          f"path by default, so the default rows say what a user gets and the (alone) rows what the sampler finds "
          f"by itself. in time = exact and returned within time_limit + {1000 * _real_plans.OVERRUN_S:.0f} ms. "
          f"grid's path = the path returned is the grid planner's (its message says so, or its cost equals the "
          f"grid's).\n")
    print(_md(["planner", "exact", "in time", "grid's path", "first solution p50 (max) ms", "plan time p50 (max) ms",
               "cost / grid p50 (min-max)", "least clearance m", "too close"],
              [_planner_row(runs, p, clear_min, time_limit) for p in order]))
    print("\nper log (exact; cost / grid p50):\n")
    rows = []
    for p in order:
        row = [p]
        for rm in maps:
            mine = [r for r in runs if r.log == rm.name]
            n = sum(r.label == p for r in mine)
            k = sum(r.label == p and r.exact for r in mine)
            ratios = _real_plans.cost_ratios(mine, p)
            row.append(f"{k}/{n}; {statistics.median(ratios):.3f}" if ratios else f"{k}/{n}; -")
        rows.append(row)
    print(_md(["planner", *[rm.name for rm in maps]], rows))
    stops = []
    for p in order[1:]:
        counts: dict[str, int] = {}
        for r in runs:
            if r.label == p and r.stopped_by:
                counts[r.stopped_by] = counts.get(r.stopped_by, 0) + 1
        if counts:
            stops.append(f"  {p}: " + ", ".join(f"{k} {n}" for k, n in sorted(counts.items())))
    if stops:
        print("\nwhat ended the search (PlanResult.stopped_by):")
        print("\n".join(stops))
    notes = [line for p in order for line in _notes(runs, p)]
    if notes:
        print("\nwhat the plans said (non-empty messages, with counts):")
        print("\n".join(notes))
    late = [r for r in runs if r.plan_s > time_limit + _real_plans.OVERRUN_S]
    if late:
        print(f"\nplans over time_limit + {1000 * _real_plans.OVERRUN_S:.0f} ms: "
              + "; ".join(f"{r.label} on {r.log} pair {r.pair}: {_ms(r.plan_s)} ms ({r.status})" for r in late))

    # the same search by pyastar2d and scikit-image
    _real_plans.warm_baselines()
    timings: list = []
    for rm in maps:
        timings += _real_plans.grid_baselines(rm, repeats)
    print(f"\n### Grid search against pyastar2d and scikit-image, same cost grid (best of {repeats} per query)\n")
    print("cost grid: 1 + risk_weight x dilated risk where the robot's footprint is valid, inf elsewhere. "
          "ours search = grid_search.grid_path on a ready PackedGrid; ours plan = plan(..., 'grid') (packing, "
          "search, shortcut, verification); pyastar2d = astar_path (its wrapper copies the grid and checks its "
          "minimum each call), C core = its C entry point on a ready flat grid; skimage = route_through_array "
          "(Dijkstra, geometric). pyastar2d charges the entered cell's weight per step (not our edge cost), so its "
          "costs are not compared, only times and success; scikit-image's geometric cost is our edge cost, so its "
          "optimum checks our A*'s.\n")
    grows = []
    for label, ts in [*[(rm.name, [t for t in timings if t.log == rm.name]) for rm in maps], ("all", timings)]:
        if not ts:
            continue
        ratios = [t.ratio for t in ts]
        rel = [abs(t.ours_graph_cost - t.skimage_cost) / t.skimage_cost for t in ts
               if t.ours_found and t.skimage_found]
        grows.append([
            label, str(len(ts)),
            f"{sum(t.ours_found for t in ts)} / {sum(t.pyastar_found for t in ts)} / {sum(t.skimage_found for t in ts)}",
            _ms(_real_plans.p50([t.ours_search for t in ts])), _ms(_real_plans.p50([t.ours_plan for t in ts])),
            _ms(_real_plans.p50([t.pyastar for t in ts])), _ms(_real_plans.p50([t.pyastar_core for t in ts])),
            _ms(_real_plans.p50([t.skimage for t in ts])),
            f"{statistics.median(ratios):.2f} ({sum(r <= 1.0 for r in ratios)}/{len(ratios)} <= 1)",
            f"{_real_plans.p50([t.ours_plan / t.pyastar for t in ts]):.2f}",
            f"{max(rel):.1e}" if rel else "-",
        ])
    print(_md(["log", "queries", "found ours / pyastar2d / skimage", "ours search p50 ms", "ours plan p50 ms",
               "pyastar2d p50 ms", "pyastar2d C core p50 ms", "skimage p50 ms", "ours search / pyastar2d p50",
               "ours plan / pyastar2d p50", "our A* cost vs skimage optimum, max rel. diff"], grows))

    # over HTTP
    hmaps: list = []
    if http:
        http_planners = [p for p in _real_plans.HTTP_PLANNERS if p == "grid" or p in planners] or ["grid"]
        now_version = _real_plans.code_version()
        if now_version != version:
            print(f"\nWARNING: the code changed during the run ({version} -> {now_version}): the service starts "
                  "on the new code, this process plans on the old")
        print(f"\n### Over HTTP: the same queries as POST /maps/{{name}}/plan ({', '.join(http_planners)}), each "
              "beside the same plan() in this process\n", flush=True)
        hmaps = _real_plans.http_plans(maps, http_planners, time_limit, repeats,
                                       log=lambda m: print(m, flush=True))
        print()
        for hm in hmaps:
            print(f"- {hm.log} ({hm.cells / 1e6:.2f} M cells): built on the service by app.import_log --url in "
                  f"{hm.import_s:.1f} s; risk grid equal to ours: {'yes' if hm.risk_equal else 'NO'} (max |diff| "
                  f"{hm.risk_max_diff:.3g}); a new RiskField's dilation and valid mask (each worker plan builds one): "
                  f"{1000 * hm.fresh_field_s:.0f} ms")
        print()
        hrows = []
        for p in http_planners:
            for label, hs in [*[(hm.log, [r for r in hm.runs if r.planner == p]) for hm in hmaps],
                              ("all", [r for hm in hmaps for r in hm.runs if r.planner == p])]:
                if not hs:
                    continue
                same = sum(abs(r.http_cost - r.local_cost) <= 1e-9 * max(1.0, abs(r.local_cost)) for r in hs)
                diffs = [r.http_s - r.local_s for r in hs]
                hrows.append([
                    label, p, str(len(hs)),
                    f"{sum(r.http_status == 'exact' for r in hs)} / {sum(r.local_status == 'exact' for r in hs)}",
                    f"{same}/{len(hs)}", _ms(_real_plans.p50([r.local_s for r in hs])),
                    _ms(_real_plans.p50([r.http_s for r in hs])),
                    f"{_ms(_real_plans.p50(diffs))} ({_ms(_real_plans.percentile(diffs, 90))})",
                    _ms(_real_plans.p50([r.worker_s for r in hs])),
                ])
        print(_md(["log", "planner", "samples", "exact HTTP / here", "same cost", "here p50 ms", "HTTP p50 ms",
                   "HTTP - here p50 (p90) ms", "plan() in the worker p50 ms"], hrows))

    # targets
    print("\ntargets:")
    for p in order[1:]:
        mine = [r for r in runs if r.label == p]
        k = sum(r.in_time(time_limit) for r in mine)
        ok = bool(mine) and k >= 0.95 * len(mine)
        # the target is on what plan() gives by default; a sampler alone is printed for reference
        verdict = ("at or above 95 %" if ok else "below 95 %") + " (for reference: not a target)" if any(
            r.alone for r in mine) else ("met" if ok else "NOT met")
        print(f"  {p} exact on >= 95 % of queries within {time_limit:g} s (+ {1000 * _real_plans.OVERRUN_S:.0f} ms): "
              f"{_frac(k, len(mine))}, longest plan {_ms(max((r.plan_s for r in mine), default=math.nan))} ms: "
              f"{verdict}")
    if timings:
        ratio = statistics.median([t.ratio for t in timings])
        n_ok = sum(t.ratio <= 1.0 for t in timings)
        print(f"  our grid search time <= pyastar2d's on the same cost grid (median of per-query ratios): {ratio:.2f} "
              f"({n_ok}/{len(timings)} queries <= 1; our whole grid plan: "
              f"{_real_plans.p50([t.ours_plan / t.pyastar for t in timings]):.2f}; against pyastar2d's C core: "
              f"{_real_plans.p50([t.ours_search / t.pyastar_core for t in timings]):.2f}): "
              f"{'met' if ratio <= 1.0 else 'NOT met'}")
    if hmaps:
        sizes = [hm.cells / 1e6 for hm in hmaps]
        for p in sorted({r.planner for hm in hmaps for r in hm.runs}, key=order.index):
            hs = [r for hm in hmaps for r in hm.runs if r.planner == p]
            here, over = _real_plans.p50([r.local_s for r in hs]), _real_plans.p50([r.http_s for r in hs])
            print(f"  {p} over HTTP p50 <= in-process p50 + 50 ms ({min(sizes):.2f}-{max(sizes):.2f} M-cell maps): "
                  f"{_ms(over)} vs {_ms(here)} ms, +{_ms(over - here)} ms: "
                  f"{'met' if over <= here + 0.050 else 'NOT met'}")
        if not all(hm.risk_equal for hm in hmaps):
            print("  (the service's risk differs from ours on: "
                  + ", ".join(hm.log for hm in hmaps if not hm.risk_equal) + ")")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer runs and planners (both sections), one real log")
    parser.add_argument("--seed", type=int, default=2024, help="map generator seed")
    parser.add_argument("--runs", type=int, default=None, help="runs per planner and map")
    parser.add_argument("--time-limit", type=float, default=1.0, help="seconds per plan")
    real = parser.add_argument_group("real maps: run after the synthetic maps unless told otherwise")
    part = real.add_mutually_exclusive_group()
    part.add_argument("--real-only", action="store_true", help="only the real-map section")
    part.add_argument("--synthetic-only", action="store_true", help="only the synthetic maps")
    _data.add_option(real)
    real.add_argument("--logs", default=None,
                      help=f"logs of the data directory, comma-separated (default {','.join(_real_plans.DEFAULT_LOGS)}; "
                           f"--quick: {','.join(_real_plans.QUICK_LOGS)})")
    real.add_argument("--pairs", type=int, default=None,
                      help=f"queries per log (default {_real_plans.PAIRS}; --quick: {_real_plans.QUICK_PAIRS})")
    real.add_argument("--planners", default=None,
                      help=f"sampling planners, comma-separated (default those of {','.join(_real_plans.SAMPLING)} "
                           f"available; --quick: {','.join(_real_plans.QUICK_SAMPLING)})")
    real.add_argument("--repeats", type=int, default=3, help="grid timings: best of this many (and HTTP grid "
                      "samples per query; default 3)")
    real.add_argument("--no-http", action="store_true", help="skip the service (HTTP) part")
    real.add_argument("--no-alone", action="store_true", help="skip the sampling planners' runs with "
                      "grid_seed=False (the sampler on its own, beside plan()'s default that seeds it with the grid's path)")
    args = parser.parse_args()
    _data.use(args)
    if args.logs is not None:  # checked before minutes of synthetic maps
        for name in args.logs.split(","):
            _real_plans.log_path(name)
    if args.planners is not None:
        unknown = [p for p in args.planners.split(",") if p not in available_planners() or p == "grid"]
        if unknown:
            parser.error(f"--planners: not sampling planners here: {', '.join(unknown)}; choose from "
                         f"{', '.join(p for p in available_planners() if p != 'grid')}")
    if not args.real_only:
        synthetic(args)
    if not args.synthetic_only:
        if not args.real_only:
            print()
        logs = args.logs.split(",") if args.logs else list(_real_plans.QUICK_LOGS if args.quick
                                                           else _real_plans.DEFAULT_LOGS)
        pairs = args.pairs or (_real_plans.QUICK_PAIRS if args.quick else _real_plans.PAIRS)
        default = _real_plans.QUICK_SAMPLING if args.quick else _real_plans.SAMPLING
        planners = (args.planners.split(",") if args.planners
                    else [p for p in default if p in available_planners()])
        warm_up("R2")
        real_maps(logs, pairs, planners, args.time_limit, args.repeats, not args.no_http, not args.no_alone)


def synthetic(args: argparse.Namespace) -> None:
    """The synthetic maps: planners against the grid optimum, and the objective's overhead."""
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
