"""The plan audit of ``bench_maps``: plans on our map, checked against OctoMap's occupied cells.

Pairs of poses the robot really drove (the laser poses of the log), far apart: ``PAIRS`` starts
spread evenly over the log, each the first pose from its spread position whose footprint is
valid on our map (``RiskField.valid_mask``, what ``plan`` asks of a start), and as goal the
first pose after it in log order (wrapping around) that is valid too and at least ``MIN_APART``
of the map's diagonal away. Both the grid planner (the optimum on the 8-connected cell graph,
then shortcut) and RRTstar (1 s, seeded with the pair's number) plan on our map's risk, with the
planner library's defaults: robot radius 0.2 m, ``max_risk`` 0.45 (``DEFAULT_MAX_RISK``: observed
cells with net free evidence), risk weight 1, never-observed space allowed.

Every returned path (exact or approximate: a robot would drive either) is densified to half a
cell, and its clearance is the least distance from the cell of a path point to an OctoMap-occupied
cell, centre to centre (``scipy.ndimage.distance_transform_edt``). A path is clear when that is
at least the robot radius minus one cell (the cell-size slack of comparing two grids).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fuzzyocc import GridSpec
from planning.field import DEFAULT_MAX_RISK

ROBOT_RADIUS = 0.2  # planning.plan's default (and bench_planning's)
MAX_RISK = DEFAULT_MAX_RISK
TIME_LIMIT = 1.0
PAIRS = 5
MIN_APART = 0.3  # of the map's diagonal
PLANNERS = ("RRTstar", "grid")
#: A reproducible RRTstar: this many iterations (about what 1 s holds on an idle machine) with a
#: time limit they never reach
FIXED_ITERATIONS = 25_000
FIXED_TIME_LIMIT = 60.0


@dataclass(frozen=True)
class PlanCheck:
    """One plan and its audit."""

    pair: int
    planner: str
    start: tuple[float, float]
    goal: tuple[float, float]
    apart: float  # metres between start and goal
    status: str  # "exact", "approximate", "none", or a PlanError code
    cost: float  # nan without a path
    clearance: float  # metres to the nearest OctoMap-occupied cell; nan without a path
    note: str = ""  # the planner's message (e.g. the seeded budget overrun by the clock)

    @property
    def found(self) -> bool:
        return self.status == "exact"

    @property
    def has_path(self) -> bool:
        return self.status in ("exact", "approximate")

    def clear(self, resolution: float) -> bool:
        """The path keeps the robot radius minus one cell from OctoMap's occupied cells."""
        return self.has_path and self.clearance >= ROBOT_RADIUS - resolution - 1e-9


def pick_pairs(poses: np.ndarray, valid: np.ndarray, spec: GridSpec, pairs: int = PAIRS,
               min_apart: float = MIN_APART) -> list[tuple[int, int]]:
    """(start, goal) indices into ``poses`` ((N, 2)), by the rule of the module docstring."""
    n = len(poses)
    cells = np.floor((poses - np.asarray(spec.origin)) / spec.resolution).astype(int)
    inside = np.all((cells >= 0) & (cells < np.asarray(spec.shape)), axis=1)
    ok = np.zeros(n, dtype=bool)
    ok[inside] = valid[cells[inside, 0], cells[inside, 1]]
    far = min_apart * math.hypot(*spec.size)
    out: list[tuple[int, int]] = []
    for k in range(pairs):
        start = next((i for i in range(int((k + 0.5) * n / pairs), n) if ok[i]), None)
        if start is None:
            continue
        goal = next((j % n for j in range(start + 1, start + n)
                     if ok[j % n] and np.hypot(*(poses[j % n] - poses[start])) >= far), None)
        if goal is not None and (start, goal) not in out:
            out.append((start, goal))
    return out


def clearance_map(occupied: np.ndarray, resolution: float) -> np.ndarray:
    """Metres from each cell's centre to the nearest occupied cell's centre (inf when none is)."""
    if not occupied.any():
        return np.full(occupied.shape, np.inf)
    return ndimage.distance_transform_edt(~occupied) * resolution


def path_clearance(path: np.ndarray, spec: GridSpec, clearance: np.ndarray) -> float:
    """Least clearance over the cells of ``path`` ((K, >= 2), map frame) densified to half a cell."""
    pts = np.asarray(path, dtype=np.float64)[:, :2]
    if len(pts) > 1:
        seg = np.diff(pts, axis=0)
        pieces = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / (0.5 * spec.resolution)).astype(int))
        owner = np.repeat(np.arange(len(seg)), pieces)
        frac = (np.arange(owner.size) - (np.cumsum(pieces) - pieces)[owner]) / pieces[owner]
        pts = np.vstack([pts[owner] + frac[:, None] * seg[owner], pts[-1:]])
    cells = np.floor((pts - np.asarray(spec.origin)) / spec.resolution).astype(int)
    cells = np.clip(cells, 0, np.asarray(spec.shape) - 1)  # a path never leaves the map; rounding at its edge
    return float(clearance[cells[:, 0], cells[:, 1]].min())


def audit(risk: np.ndarray, observed: np.ndarray, spec: GridSpec, poses: np.ndarray, octo_occupied: np.ndarray,
          pairs: int = PAIRS, planners: tuple[str, ...] = PLANNERS, time_limit: float = TIME_LIMIT,
          max_iterations: int | None = None) -> list[PlanCheck]:
    """Plan between far-apart driven poses on ``risk`` and audit every path against ``octo_occupied``.

    ``max_iterations`` bounds the sampling planners' solves by a count as well (``plan``'s own
    argument): with a ``time_limit`` the count never reaches, the seeded plans repeat exactly
    whatever the machine's load (the CI test's setting).
    """
    from planning import PlanError, RiskField, plan  # OMPL: only a process that audits plans loads it

    field = RiskField(np.asarray(risk, dtype=np.float32), spec.resolution, spec.origin, observed=np.asarray(observed))
    valid = field.valid_mask(ROBOT_RADIUS, MAX_RISK)
    clearance = clearance_map(octo_occupied, spec.resolution)
    out: list[PlanCheck] = []
    for k, (i, j) in enumerate(pick_pairs(poses, valid, spec, pairs)):
        start, goal = (float(poses[i, 0]), float(poses[i, 1])), (float(poses[j, 0]), float(poses[j, 1]))
        apart = float(np.hypot(goal[0] - start[0], goal[1] - start[1]))
        for planner in planners:
            try:
                r = plan(field, start, goal, planner=planner, time_limit=time_limit, robot_radius=ROBOT_RADIUS,
                         max_risk=MAX_RISK, seed=k, max_iterations=None if planner == "grid" else max_iterations)
            except PlanError as exc:  # not expected: both poses were checked valid
                out.append(PlanCheck(k, planner, start, goal, apart, exc.code, math.nan, math.nan, exc.message))
                continue
            has_path = r.status in ("exact", "approximate") and len(r.path)
            out.append(PlanCheck(k, planner, start, goal, apart, r.status, float(r.cost) if has_path else math.nan,
                                 path_clearance(r.path, spec, clearance) if has_path else math.nan, r.message))
    return out
