"""The dynamic-obstacle case of ``bench_maps``: an obstacle seen in a few scans, then gone.

On a real log, after the training scans are fused, a few real scans spread over the log (chosen
deterministically) each get a small box (0.4 m x 0.4 m, on the grid's cells) in the free space
in front of the laser, where every beam crossing the box reads at least 1.5 m beyond it (a
no-return, "nothing within range", counts as beyond: a person standing in front of an open
door or a long hall; each trial records how many of its beams were no-returns, since a map may
choose not to clear occupied cells on them, as Nav2's ``inf_is_valid: false`` does). The
beams that cross the box read the box's range instead; that modified scan is fused ``SEEN``
times (a person stands there for a moment), then the unmodified scan over and over (the person
has left), counting the scans until no cell the obstacle made occupied is occupied any more,
up to ``CAP``.

The cells. The box and a margin of ``TOLERANCE_CELLS`` around it (a map may place a surface a
cell or two off, or thicken it) must hold no occupied cell in any map before the trial; the
cells checked are those of that region that *any* of the three maps marks occupied after the
obstacle's scans, the same set for every map. "Occupied" is risk >= 0.6 (``OCCUPIED``, the
planner's default ``max_risk``) for ours and ``BayesMap``, ``isNodeOccupied`` for OctoMap. A map
that never marked the obstacle is reported as not having seen it (its count is 0: there was
nothing to clear).

Each trial starts from each map's own map of the training scans: ``FuzzyMap`` and ``BayesMap``
are copied per trial (``copy_map``). OctoMap's tree is not copied: its update of a cell
(``insertPointCloud``: the end cells of the beams as hits, the cells the beams cross as misses,
each a log-odds step clamped per cell) depends only on that cell's own log-odds and on the
scan, so each trial runs in a new tree holding the training tree's values of the checked
region's cells, with the same box limit, sensor model, height and beam reach. That gives the
very counts a full copy of the tree gives (``tests/bench/test_map_quality.py`` checks it) at a
small fraction of the cost (a full copy of a large log's tree takes seconds to write and read).
"""

from __future__ import annotations

import copy
import math
import statistics
import tempfile
from dataclasses import dataclass

import numpy as np

from bench._logmaps import OCCUPIED, TOLERANCE_CELLS, _z, insert_scan
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan

BOX_M = 0.4
CLEAR_BEYOND_M = 1.5  # every beam crossing the box reads at least this far beyond it
SEEN = 3  # scans the obstacle is seen in
CAP = 50  # unmodified scans fused at most; a count of CAP + 1 means "not cleared"
TRIALS = 5
MODELS = ("FuzzyMap", "BayesMap", "OctoMap")
# placements tried in front of the laser, in this order: bearing (deg from the laser's axis), distance (m)
_BEARINGS_DEG = (0, 10, -10, 20, -20, 30, -30, 40, -40, 50, -50, 60, -60)
_DISTANCES_M = (2.0, 2.5, 1.5, 3.0, 3.5, 4.0)
_SCANS_TRIED = 30  # scans after a trial's spread position searched for a placement


@dataclass(frozen=True)
class Trial:
    """One obstacle: where, and how each map saw and cleared it."""

    scan_index: int  # in the fused scans
    box: tuple[float, float, float, float]  # x0, y0, x1, y1 (map frame, on cell boundaries)
    beams: int  # beams of the scan that hit the box
    no_returns: int  # of them, beams that were no-returns in the real scan (nothing in range behind the box)
    cells: int  # cells checked (occupied in some map after the obstacle's scans)
    seen: dict[str, bool]  # the map marked some cell of the region occupied
    scans_to_clear: dict[str, int]  # CAP + 1: not cleared within CAP scans


def _box_hits(scan: LaserScan, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per beam of ``scan``: crosses the box, entry range, exit range (slab method)."""
    x, y, theta = scan.pose
    angles = theta + scan.angle_min + np.arange(scan.ranges.size) * scan.angle_increment
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    o = np.array([x, y])
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - o) / d
        tb = (hi - o) / d
    # a direction parallel to a slab: inside it for every t, or never
    inside = (o >= lo) & (o <= hi)
    t0 = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    t1 = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    near, far = t0.max(axis=1), t1.min(axis=1)
    return (near <= far) & (near > 0.0), near, far


def place_box(scan: LaserScan, spec: GridSpec, occupied_before: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The first box (lower, upper corners) in front of the laser that fits the protocol, or None.

    Fits: on whole cells, inside the map with its margin, at least 3 beams cross it, every
    beam crossing it is valid and reads ``CLEAR_BEYOND_M`` beyond its far side, and no cell of
    the box and its margin is in ``occupied_before``.
    """
    res = spec.resolution
    n = round(BOX_M / res)
    origin = np.asarray(spec.origin)
    shape = np.asarray(spec.shape)
    x, y, theta = scan.pose
    r = scan.ranges
    valid = r >= scan.range_min  # False for NaN too; a no-return (+inf or range_max) reads beyond anything
    reading = np.where(r >= scan.range_max, np.inf, r)
    for bearing in _BEARINGS_DEG:
        a = theta + math.radians(bearing)
        for dist in _DISTANCES_M:
            centre = np.array([x + dist * math.cos(a), y + dist * math.sin(a)])
            cell0 = np.round((centre - origin) / res - n / 2).astype(int)
            m = TOLERANCE_CELLS
            if np.any(cell0 - m < 0) or np.any(cell0 + n + m > shape):
                continue
            lo, hi = origin + cell0 * res, origin + (cell0 + n) * res
            crosses, _, far = _box_hits(scan, lo, hi)
            if crosses.sum() < 3 or not np.all(valid[crosses]):
                continue
            if np.any(reading[crosses] < far[crosses] + CLEAR_BEYOND_M):
                continue
            (i0, j0), (i1, j1) = cell0 - m, cell0 + n + m
            if occupied_before[i0:i1, j0:j1].any():
                continue
            return lo, hi
    return None


def with_box(scan: LaserScan, lo: np.ndarray, hi: np.ndarray) -> tuple[LaserScan, int, int]:
    """``scan`` with the beams that cross the box reading the box's range; how many they are, and how
    many of them were no-returns."""
    crosses, near, _ = _box_hits(scan, lo, hi)
    ranges = np.where(crosses, near, scan.ranges)
    return (LaserScan(pose=scan.pose, angle_min=scan.angle_min, angle_increment=scan.angle_increment,
                      ranges=ranges, range_min=scan.range_min, range_max=scan.range_max,
                      registration_sigma=scan.registration_sigma),
            int(crosses.sum()), int(np.sum(crosses & (scan.ranges >= scan.range_max))))


# ------------------------------------------------------------------ the three maps
class _GridModel:
    """Ours or BayesMap: a copy of the trained map per trial, occupied = risk >= OCCUPIED."""

    def __init__(self, trained: FuzzyMap | BayesMap) -> None:
        self.trained = trained
        self.spec = trained.spec

    def fresh(self, cells: np.ndarray) -> FuzzyMap | BayesMap:
        return copy_map(self.trained)

    def fuse(self, model: FuzzyMap | BayesMap, scans: list[LaserScan]) -> None:
        model.integrate_batch(scans)

    def occupied(self, model: FuzzyMap | BayesMap, cells: np.ndarray) -> np.ndarray:
        centres = np.asarray(self.spec.origin) + (cells + 0.5) * self.spec.resolution
        return model.risk_at(centres) >= OCCUPIED


class _OctoModel:
    """OctoMap: a new tree per trial holding the trained tree's values of the cells that matter."""

    def __init__(self, tree, spec: GridSpec, full_copy: bool = False) -> None:  # type: ignore[no-untyped-def]
        self.tree = tree
        self.spec = spec
        self.full_copy = full_copy
        self.z = _z(spec)
        self.reach = float(np.hypot(*np.subtract(spec.upper, spec.origin)))  # as octomap_tree

    def _coords(self, cells: np.ndarray) -> np.ndarray:
        xy = np.asarray(self.spec.origin) + (cells + 0.5) * self.spec.resolution
        return np.column_stack([xy, np.full(len(xy), self.z)])

    def fresh(self, cells: np.ndarray):  # type: ignore[no-untyped-def]
        import octomap

        spec = self.spec
        if self.full_copy:  # the slow reference the local copy is checked against
            with tempfile.TemporaryDirectory() as tmp:
                self.tree.write(f"{tmp}/trained.ot")
                local = octomap.OcTree.read(f"{tmp}/trained.ot")
        else:
            local = octomap.OcTree(spec.resolution)
        local.setBBXMin(np.array([spec.origin[0], spec.origin[1], 0.0]))  # as octomap_tree
        local.setBBXMax(np.array([spec.upper[0], spec.upper[1], spec.resolution * 0.999]))
        local.useBBXLimit(True)
        if self.full_copy:
            return local
        for c in self._coords(cells):
            try:
                value = self.tree.search(c).getLogOdds()
            except octomap.NullPointerException:  # unknown in the trained tree: unknown here too
                continue
            local.updateNode(c, float(value))  # from 0 (unknown): the value itself, within the clamps
        return local

    def fuse(self, tree, scans: list[LaserScan]) -> None:  # type: ignore[no-untyped-def]
        for s in scans:
            insert_scan(tree, s, self.z, self.reach)

    def occupied(self, tree, cells: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
        import octomap

        out = np.zeros(len(cells), dtype=bool)
        for k, c in enumerate(self._coords(cells)):
            try:
                out[k] = tree.isNodeOccupied(tree.search(c))
            except octomap.NullPointerException:
                pass
        return out


def copy_map(trained: FuzzyMap | BayesMap) -> FuzzyMap | BayesMap:
    """An independent copy of a map, the engine shared (it is immutable).

    The same map, bit for bit, as ``from_arrays(to_arrays())`` (tested), and it keeps the risk
    cache: a restored large map recomputes every cell's risk at its first read (over a second
    for a 5000 x 5000 Bayes map), once per trial and model.
    """
    engine = getattr(trained, "engine", None)
    return copy.deepcopy(trained, memo={id(engine): engine} if engine is not None else None)


def occupied_grid(risk: np.ndarray) -> np.ndarray:
    return np.asarray(risk) >= OCCUPIED


def run_trials(fused: list[LaserScan], spec: GridSpec, fuzzy: FuzzyMap, bayes: BayesMap,  # type: ignore[no-untyped-def]
               tree, octo_occupied: np.ndarray, trials: int = TRIALS, seen: int = SEEN, cap: int = CAP,
               octomap_full_copy: bool = False) -> list[Trial]:
    """The dynamic-obstacle trials on maps of ``fused`` (left unchanged): one per placement found.

    ``octo_occupied`` is ``octomap_occupied(tree, spec)``; the trials' scans are spread evenly
    over ``fused``, each the first scan from its spread position (up to ``_SCANS_TRIED`` on) that
    has room for a box. ``octomap_full_copy``: start each OctoMap trial from a full copy of
    ``tree`` (written and read back) instead of the local one (same counts, far slower).
    """
    before = occupied_grid(fuzzy.risk()) | occupied_grid(bayes.risk()) | octo_occupied
    models = {"FuzzyMap": _GridModel(fuzzy), "BayesMap": _GridModel(bayes),
              "OctoMap": _OctoModel(tree, spec, octomap_full_copy)}
    res = spec.resolution
    out: list[Trial] = []
    used: set[int] = set()
    for t in range(trials):
        start = int((t + 0.5) * len(fused) / trials)
        for index in range(start, min(start + _SCANS_TRIED, len(fused))):
            if index in used:
                continue
            box = place_box(fused[index], spec, before)
            if box is not None:
                break
        else:
            continue
        used.add(index)
        lo, hi = box
        scan = fused[index]
        obstacle, beams, no_returns = with_box(scan, lo, hi)
        c0 = np.round((lo - np.asarray(spec.origin)) / res).astype(int) - TOLERANCE_CELLS
        c1 = np.round((hi - np.asarray(spec.origin)) / res).astype(int) + TOLERANCE_CELLS
        ii, jj = np.meshgrid(np.arange(c0[0], c1[0]), np.arange(c0[1], c1[1]), indexing="ij")
        region = np.column_stack([ii.ravel(), jj.ravel()])
        maps, after = {}, {}
        for name, model in models.items():
            m = model.fresh(region)
            model.fuse(m, [obstacle] * seen)
            maps[name], after[name] = m, model.occupied(m, region)
        cells = region[np.logical_or.reduce(list(after.values()))]
        counts = {}
        for name, model in models.items():
            m, n = maps[name], 0
            while len(cells) and model.occupied(m, cells).any():
                if n == cap:
                    n = cap + 1
                    break
                model.fuse(m, [scan])
                n += 1
            counts[name] = n
        out.append(Trial(scan_index=index, box=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
                         beams=beams, no_returns=no_returns, cells=len(cells),
                         seen={k: bool(v.any()) for k, v in after.items()}, scans_to_clear=counts))
    return out


def summary(trials: list[Trial], name: str) -> str:
    """``median / max`` scans to clear for one map, ``>CAP`` when not cleared, with unseen obstacles noted."""
    if not trials:
        return "no trial"
    counts = [t.scans_to_clear[name] for t in trials]

    def fmt(n: int) -> str:
        return f">{CAP}" if n > CAP else str(n)

    text = f"{fmt(statistics.median_high(counts))} / {fmt(max(counts))}"
    unseen = sum(not t.seen[name] for t in trials)
    return text + (f" ({unseen} of {len(trials)} unseen)" if unseen else "")
