"""Planning on maps of real buildings: the instrument of ``bench_planning``'s real-map section.

A map per recorded CARMEN log of the data directory (``bench/_logmaps.py``, ``--data``): every scan of the log fused in log order, in
batches of 32 (what ``app.cli.import_log`` posts), into ``FuzzyMap(spec)`` (the default preset and
sensor model, as the service builds a new map), 0.05 m cells. Queries: ``_plan_audit.pick_pairs``,
pairs of laser poses the robot drove, at least 30 % of the map's diagonal apart, both valid starts
(robot radius 0.2 m, ``max_risk`` 0.45: ``plan``'s defaults).

Three measurements, each a function here:

- :func:`run_planners`: every planner named on every query, ``time_limit`` 1 s, seeded with the
  pair's number (so a run repeats while the seeded budget, not the clock, ends the solve); per plan
  its status, time to first solution, wall time, cost, and its clearance: the least distance from a
  cell of the path (densified to half a cell) to a cell of our own map at risk >= 0.6, centre to
  centre (``_plan_audit.path_clearance``). The grid planner's cost on the same query is the
  yardstick of cost.
- :func:`grid_baselines`: the same search on the same cost grid by pyastar2d (``astar_path``, and
  its C entry point alone, without the wrapper's copy and checks) and by scikit-image's
  ``route_through_array`` (Dijkstra, ``geometric=True``), beside our grid search
  (``grid_search.grid_path`` on a ready ``PackedGrid``) and our whole ``plan(..., "grid")``, each
  best of ``repeats``. The cost grid: ``1 + risk_weight * dilated_risk`` where the robot's footprint
  is valid, ``inf`` (impassable) elsewhere. scikit-image's geometric cost of a step,
  ``(c_a + c_b) / 2 * |step|``, is exactly our edge cost in cells, so its optimum checks our A*'s
  (``graph_cost``); pyastar2d charges the entered cell's weight per step, a slightly different
  cost model, so its paths are compared by success only.
- :func:`http_plans`: the service (``python -m app`` on a free port, a temporary data directory),
  the same map built there by ``python -m app.import_log LOG --url ...`` (its risk compared with
  ours), then the same queries as ``POST /maps/{name}/plan``, each beside the same ``plan`` call
  in this process (interleaved), wall time as the client sees it.
"""

from __future__ import annotations

import math
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench import _data, _logmaps, _plan_audit
from fuzzyocc import FuzzyMap, GridSpec

ROBOT_RADIUS = _plan_audit.ROBOT_RADIUS  # 0.2 m, plan's default
MAX_RISK = _plan_audit.MAX_RISK  # 0.45, plan's default
OCCUPIED = _logmaps.OCCUPIED  # clearance is measured to cells at or above this risk
RISK_WEIGHT = 1.0
TIME_LIMIT = 1.0
FUSE_BATCH = 32  # app.import_log's default batch: the service's map is fused in the same batches
#: The logs whose maps are 1.3-2.1 M cells (belgioioso 727 x 1882, csail 1167 x 1735, orebro 1502 x 1330)
DEFAULT_LOGS = ("belgioioso", "csail", "orebro")
QUICK_LOGS = ("belgioioso",)
PAIRS = 10
QUICK_PAIRS = 4
#: The sampling planners a user would pick: RRTstar (the default), RRTConnect (fast, feasible), and the
#: informed / batch variants (those ``available_planners()`` lists are run)
SAMPLING = ("RRTstar", "RRTConnect", "InformedRRTstar", "SORRTstar", "BITstar")
QUICK_SAMPLING = ("RRTstar", "RRTConnect")
HTTP_PLANNERS = ("grid", "RRTstar")
SERVICE_BATCH = 32
#: A plan counts as in time when it returns within its time limit plus this (the synthetic section's bound)
OVERRUN_S = 0.1
#: What ``plan`` says when a sampling planner's result is the grid planner's path it was seeded with
GRID_SEED_NOTE = "the path is the grid planner's seed"
ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------- maps and queries


@dataclass(frozen=True)
class Query:
    pair: int  # the pair's number: the seed of its sampling plans
    start: tuple[float, float]
    goal: tuple[float, float]

    @property
    def apart(self) -> float:
        return math.hypot(self.goal[0] - self.start[0], self.goal[1] - self.start[1])


@dataclass
class RealMap:
    """One log's map, ready to plan on."""

    name: str
    path: Path
    scans: int
    spec: GridSpec
    risk: np.ndarray  # float32, as FuzzyMap.risk()
    observed: np.ndarray
    fuse_s: float
    queries: list[Query]
    field: Any  # planning.RiskField
    clearance: np.ndarray  # metres from each cell's centre to the nearest cell at risk >= OCCUPIED

    @property
    def cells(self) -> int:
        return int(np.prod(self.spec.shape))


def log_path(name: str) -> Path:
    """The log of that name (``csail`` or ``csail-corrected.log.gz``) in the data directory (``--data``);
    SystemExit listing the names."""
    paths = {_logmaps.log_name(p): p for p in _logmaps.log_paths()}
    key = _logmaps.log_name(Path(name)) if name.endswith(".log.gz") else name
    if key not in paths:
        raise SystemExit(f"no log named {name!r} in {_logmaps.log_dir()} ({_data.describe()}; another with "
                         f"{_data.OPTION} DIR); the logs are: {', '.join(sorted(paths))}")
    return paths[key]


def build_map(path: Path, pairs: int = PAIRS, scans: int | None = None) -> RealMap:
    """Fuse the log's scans (all, or the first ``scans``) and pick ``pairs`` queries on the map."""
    from planning import RiskField

    taken = _logmaps.load(path)
    if scans is not None:
        taken = taken[:scans]
    spec = _logmaps.grid_for(taken)
    t0 = time.perf_counter()
    fmap = FuzzyMap(spec)  # the default preset and sensor model: what POST /maps makes with import_log's request
    _logmaps.fuse(fmap, taken, batch=FUSE_BATCH)
    risk = np.asarray(fmap.risk(), dtype=np.float32)
    observed = np.asarray(fmap.observed(), dtype=bool)
    fuse_s = time.perf_counter() - t0
    field_ = RiskField(risk, spec.resolution, spec.origin, observed=observed)
    valid = field_.valid_mask(ROBOT_RADIUS, MAX_RISK)
    poses = np.array([s.pose[:2] for s in taken], dtype=np.float64)
    queries = [Query(k, (float(poses[i, 0]), float(poses[i, 1])), (float(poses[j, 0]), float(poses[j, 1])))
               for k, (i, j) in enumerate(_plan_audit.pick_pairs(poses, valid, spec, pairs))]
    clearance = _plan_audit.clearance_map(risk >= OCCUPIED, spec.resolution)
    return RealMap(_logmaps.log_name(path), path, len(taken), spec, risk, observed, fuse_s, queries, field_,
                   clearance)


def cell(spec: GridSpec, point: Sequence[float]) -> tuple[int, int]:
    u = np.floor((np.asarray(point[:2], dtype=np.float64) - np.asarray(spec.origin)) / spec.resolution).astype(int)
    return int(u[0]), int(u[1])


# ---------------------------------------------------------------- every planner on every query


@dataclass(frozen=True)
class PlanRun:
    log: str
    pair: int
    planner: str
    status: str  # exact / approximate / none, or a PlanError code
    first_s: float  # time to first solution (nan without one)
    plan_s: float  # PlanResult.planning_time
    wall_s: float  # around the call
    cost: float  # nan without a path
    clearance: float  # metres to our map's nearest cell at risk >= 0.6; nan without a path
    length: float
    message: str = ""
    alone: bool = False  # planned with grid_seed=False: the sampling planner on its own
    stopped_by: str = ""  # PlanResult.stopped_by where plan() reports it: what ended the search

    @property
    def exact(self) -> bool:
        return self.status == "exact"

    @property
    def label(self) -> str:
        return f"{self.planner} (alone)" if self.alone else self.planner

    def in_time(self, time_limit: float) -> bool:
        """Exact, and returned within the limit plus OVERRUN_S."""
        return self.exact and self.plan_s <= time_limit + OVERRUN_S

    def took_grid_path(self, grid_cost: float) -> bool:
        """The path returned is the grid planner's (its seed won or the sampler reached nothing: same cost)."""
        return GRID_SEED_NOTE in self.message or (
            self.exact and math.isfinite(grid_cost) and abs(self.cost - grid_cost) <= 1e-9 * grid_cost)


def can_plan_alone() -> bool:
    """Whether ``plan`` seeds sampling planners with the grid planner's path and can be told not to."""
    import inspect

    from planning import plan

    return "grid_seed" in inspect.signature(plan).parameters


def plan_once(rm: RealMap, q: Query, planner: str, time_limit: float = TIME_LIMIT,
              max_iterations: int | None = None, alone: bool = False) -> PlanRun:
    """One ``plan`` call on ``rm``, measured and audited; ``alone``: ``grid_seed=False`` (the sampler on its own)."""
    from planning import PlanError, plan

    grid = planner == "grid"
    extra = {"grid_seed": False} if alone else {}
    t0 = time.perf_counter()
    try:
        r = plan(rm.field, q.start, q.goal, planner=planner, time_limit=time_limit, robot_radius=ROBOT_RADIUS,
                 max_risk=MAX_RISK, risk_weight=RISK_WEIGHT, seed=None if grid else q.pair,
                 max_iterations=None if grid else max_iterations, **extra)
    except PlanError as exc:  # not expected: pick_pairs checked both poses
        wall = time.perf_counter() - t0
        return PlanRun(rm.name, q.pair, planner, exc.code, math.nan, wall, wall, math.nan, math.nan, math.nan,
                       exc.message, alone)
    wall = time.perf_counter() - t0
    has_path = r.status in ("exact", "approximate") and len(r.path) > 0
    clear = _plan_audit.path_clearance(r.path, rm.spec, rm.clearance) if has_path else math.nan
    return PlanRun(rm.name, q.pair, planner, str(r.status), float(r.first_solution_time), float(r.planning_time),
                   wall, float(r.cost) if has_path else math.nan, clear, float(r.length) if has_path else math.nan,
                   r.message, alone, str(getattr(r, "stopped_by", "")))


def run_planners(rm: RealMap, planners: Sequence[str], time_limit: float = TIME_LIMIT,
                 max_iterations: int | None = None, alone: bool = False,
                 progress: Callable[[PlanRun], None] | None = None) -> list[PlanRun]:
    """Every planner on every query of ``rm`` (the grid planner first: the cost yardstick).

    ``alone``: each sampling planner also runs with ``grid_seed=False`` (where ``plan`` has it), as
    ``PlanRun.alone``: what the sampler finds by itself, beside what a user gets by default.
    """
    order = ["grid", *[p for p in planners if p != "grid"]]
    variants = [False, True] if alone and can_plan_alone() else [False]
    out = []
    for q in rm.queries:
        for planner in order:
            for by_itself in variants if planner != "grid" else [False]:
                run = plan_once(rm, q, planner, time_limit, max_iterations, by_itself)
                out.append(run)
                if progress is not None:
                    progress(run)
    return out


def grid_costs(runs: Sequence[PlanRun]) -> dict[tuple[str, int], float]:
    """The grid planner's cost per (log, pair), where it was exact."""
    return {(r.log, r.pair): r.cost for r in runs if r.planner == "grid" and r.exact}


def cost_ratios(runs: Sequence[PlanRun], label: str) -> list[float]:
    """Cost / the grid planner's cost on the same query, for the exact plans of ``label`` (``PlanRun.label``)."""
    grid = grid_costs(runs)
    return [r.cost / grid[(r.log, r.pair)] for r in runs
            if r.label == label and r.exact and (r.log, r.pair) in grid]


# ---------------------------------------------------------------- the same search by pyastar2d and scikit-image


@dataclass(frozen=True)
class GridTiming:
    """Best-of-``repeats`` seconds of each search on one query, and what each found."""

    log: str
    pair: int
    ours_search: float  # grid_search.grid_path on a ready PackedGrid
    ours_plan: float  # plan(..., planner="grid"): packing, search, shortcut, verification, measures
    pyastar: float  # pyastar2d.astar_path (its wrapper copies the grid and checks its minimum each call)
    pyastar_core: float  # pyastar2d's C entry point on a ready flat grid
    skimage: float  # skimage.graph.route_through_array
    ours_found: bool
    pyastar_found: bool
    skimage_found: bool
    ours_graph_cost: float  # metres x (1 + risk), the cell chain's cost as our A* summed it
    skimage_cost: float  # the same model by Dijkstra, in metres (nan when not found)

    @property
    def ratio(self) -> float:
        """Our search's time / pyastar2d's (astar_path)."""
        return self.ours_search / self.pyastar


def cost_grid(rm: RealMap) -> np.ndarray:
    """float32 weights: 1 + w * dilated risk where the footprint is valid, inf (impassable) elsewhere."""
    dilated = rm.field.dilated_risk(ROBOT_RADIUS)
    valid = rm.field.valid_mask(ROBOT_RADIUS, MAX_RISK)
    return np.where(valid, 1.0 + RISK_WEIGHT * dilated.astype(np.float64), np.inf).astype(np.float32)


def _best(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    best, out = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def grid_baselines(rm: RealMap, repeats: int = 3) -> list[GridTiming]:
    """Our grid search, our grid plan, pyastar2d and scikit-image on each query of ``rm`` (same cost grid)."""
    import pyastar2d
    from pyastar2d import astar as pyastar_c
    from skimage.graph import route_through_array

    from planning import plan
    from planning.grid_search import grid_path
    from planning.packed import PackedGrid

    weights = cost_grid(rm)
    flat = np.ascontiguousarray(weights.ravel())
    weights64 = weights.astype(np.float64)  # the same numbers, in the dtype route_through_array works in
    packed = PackedGrid(rm.field, ROBOT_RADIUS, MAX_RISK, True, RISK_WEIGHT)
    h, w = weights.shape
    res = rm.spec.resolution

    def sk(s: tuple[int, int], g: tuple[int, int]) -> float:
        try:
            _, total = route_through_array(weights64, s, g, fully_connected=True, geometric=True)
        except ValueError:  # "no minimum-cost path was found"
            return math.nan
        return float(total)

    out = []
    for q in rm.queries:
        s, g = cell(rm.spec, q.start), cell(rm.spec, q.goal)
        si, gi = s[0] * w + s[1], g[0] * w + g[1]
        times: dict[str, float] = {}
        found: dict[str, Any] = {}
        calls: dict[str, Callable[[], Any]] = {
            "ours_search": lambda: grid_path(packed, q.start, q.goal),
            "ours_plan": lambda: plan(rm.field, q.start, q.goal, planner="grid", robot_radius=ROBOT_RADIUS,
                                      max_risk=MAX_RISK, risk_weight=RISK_WEIGHT),
            "pyastar": lambda: pyastar2d.astar_path(weights, s, g, allow_diagonal=True),
            "pyastar_core": lambda: pyastar_c.astar(flat, h, w, si, gi, True, 0),
            "skimage": lambda: sk(s, g),
        }
        for _ in range(repeats):  # interleaved rounds: other work on the machine hits every method alike
            for name, fn in calls.items():
                t, found[name] = _best(fn, 1)
                times[name] = min(times.get(name, math.inf), t)
        ours = found["ours_search"]
        out.append(GridTiming(
            rm.name, q.pair, times["ours_search"], times["ours_plan"], times["pyastar"], times["pyastar_core"],
            times["skimage"], bool(ours.reached), found["pyastar"] is not None, math.isfinite(found["skimage"]),
            float(ours.graph_cost), found["skimage"] * res,
        ))
    return out


def warm_baselines() -> None:
    """Load pyastar2d's and scikit-image's code paths once on a tiny grid (not timed)."""
    import pyastar2d
    from skimage.graph import route_through_array

    tiny = np.ones((8, 8), dtype=np.float32)
    pyastar2d.astar_path(tiny, (0, 0), (7, 7), allow_diagonal=True)
    route_through_array(tiny.astype(np.float64), (0, 0), (7, 7), fully_connected=True, geometric=True)


# ---------------------------------------------------------------- over HTTP


@dataclass(frozen=True)
class HttpRun:
    """One query over HTTP and the same ``plan`` call in this process, interleaved."""

    log: str
    pair: int
    planner: str
    http_s: float  # POST /maps/{name}/plan, request to parsed answer, as the client sees it
    worker_s: float  # the answer's planning_time: plan() inside the planner worker
    local_s: float  # the same plan() here, on the map's RiskField (its dilation cached: one field, many plans)
    http_status: str
    local_status: str
    http_cost: float
    local_cost: float


@dataclass
class HttpMap:
    log: str
    cells: int
    import_s: float  # python -m app.import_log --url, wall
    risk_equal: bool
    risk_max_diff: float
    fresh_field_s: float  # a new RiskField's dilation and valid mask: what each worker plan pays
    runs: list[HttpRun] = field(default_factory=list)


def _plan_body(q: Query, planner: str, time_limit: float) -> dict[str, Any]:
    body: dict[str, Any] = {"start": list(q.start), "goal": list(q.goal), "planner": planner,
                            "time_limit": time_limit, "robot_radius": ROBOT_RADIUS, "max_risk": MAX_RISK,
                            "risk_weight": RISK_WEIGHT}
    if planner != "grid":
        body["seed"] = q.pair
    return body


def http_plans(maps: Sequence[RealMap], planners: Sequence[str] = HTTP_PLANNERS, time_limit: float = TIME_LIMIT,
               repeats: int = 3, log: Callable[[str], None] = print) -> list[HttpMap]:
    """Build each map on a fresh service and time its queries over HTTP beside the same call in-process.

    The grid planner runs ``repeats`` times a query, the sampling planners once (seeded: the same
    iterations both ways); each sample is paired with an in-process ``plan`` of the same query run
    right before it. The service runs with its default 2 planner workers, warmed up (``/ready``).
    """
    import httpx
    from planning import RiskField

    from bench._client import ServerProcess, npy_array, wait_ready

    out: list[HttpMap] = []
    server = ServerProcess(env={"FUZZYRISK_PLAN_WORKERS": "2", "FUZZYRISK_PLAN_WARMUP": "true"})
    try:
        server.start(timeout_s=300.0)
        with httpx.Client(base_url=server.url, timeout=120.0) as client:
            wait_ready(client, 300.0)
            for rm in maps:
                t0 = time.perf_counter()
                done = subprocess.run(
                    [sys.executable, "-m", "app.import_log", str(rm.path), "--url", server.url, "--map", rm.name,
                     "--batch", str(SERVICE_BATCH)],
                    cwd=ROOT, capture_output=True, text=True, timeout=900,
                )
                import_s = time.perf_counter() - t0
                if done.returncode != 0:
                    raise RuntimeError(f"import_log into the service failed ({done.returncode}):\n{done.stderr[-2000:]}")
                served = npy_array(client.get(f"/maps/{rm.name}/risk", params={"format": "npy"}))
                equal = served.shape == rm.risk.shape and bool(np.array_equal(served, rm.risk))
                diff = (float(np.max(np.abs(served.astype(np.float64) - rm.risk)))
                        if served.shape == rm.risk.shape else math.inf)
                t0 = time.perf_counter()
                RiskField(rm.risk, rm.spec.resolution, rm.spec.origin, observed=rm.observed).valid_mask(
                    ROBOT_RADIUS, MAX_RISK)
                fresh = time.perf_counter() - t0
                hm = HttpMap(rm.name, rm.cells, import_s, equal, diff, fresh)
                log(f"bench planning: {rm.name} built on the service in {import_s:.1f} s (risk "
                    f"{'identical' if equal else f'differs, max {diff:.3g}'}); timing {len(rm.queries)} queries")
                # untimed: a first plan on the map in each of the two workers
                for _ in range(2):
                    client.post(f"/maps/{rm.name}/plan", json=_plan_body(rm.queries[0], "grid", time_limit))
                for q in rm.queries:
                    for planner in planners:
                        for _ in range(repeats if planner == "grid" else 1):
                            local = plan_once(rm, q, planner, time_limit)
                            body = _plan_body(q, planner, time_limit)
                            t0 = time.perf_counter()
                            resp = client.post(f"/maps/{rm.name}/plan", json=body)
                            answer = resp.json()
                            http_s = time.perf_counter() - t0
                            if resp.status_code == 200:
                                status, worker = str(answer["status"]), float(answer["planning_time"])
                                cost = float(answer["cost"]) if answer.get("cost") is not None else math.nan
                            else:
                                status, worker, cost = f"HTTP {resp.status_code}", math.nan, math.nan
                            hm.runs.append(HttpRun(rm.name, q.pair, planner, http_s, worker, local.wall_s, status,
                                                   local.status, cost, local.cost))
                out.append(hm)
    finally:
        server.close()
    return out


def code_version() -> str:
    """``git describe --always --dirty`` of the repository (the planner code under test), or "?"."""
    try:
        done = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "?"
    return done.stdout.strip() or "?"


def p50(values: Sequence[float]) -> float:
    vals = [v for v in values if math.isfinite(v)]
    return statistics.median(vals) if vals else math.nan


def percentile(values: Sequence[float], q: float) -> float:
    vals = [v for v in values if math.isfinite(v)]
    return float(np.percentile(vals, q)) if vals else math.nan
