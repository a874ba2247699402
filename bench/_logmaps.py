"""Maps of recorded CARMEN logs and held-out beam scoring, shared by ``bench_maps`` and the tests (the march and
the scoring also score ``bench_heldout3d``'s 3-D rays).

The protocol: fuse 9 scans of every 10 (scan ``i`` is held out when ``i % 10 == 9``);
march every held-out hit beam through the map from the laser and take the first cell at or
above the occupied threshold; compare that cell's distance with the measured range.

OctoMap gets the very same beams as points at the height of a cell centre in a 3-D ``OcTree`` at
the same resolution (it has no 2-D mode), with its default sensor model, updates limited to the
map's box (``useBBXLimit``, as our maps are bounded), and is read back with ``castRay``
(ignoring unknown cells), whose answer is also a cell centre. No-returns clear free space up to
the box for both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from bench import _data
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan
from fuzzyocc.carmen import grid_for_scans, read_carmen
from fuzzyocc.maps import Window

RESOLUTION = 0.05
MARGIN_M = 1.0
HOLDOUT_EVERY = 10
OCCUPIED = 0.6  # the planner's default max_risk: what a default plan refuses
TOLERANCE_CELLS = 2


def log_dir() -> Path:
    """The logs' folder: ``carmen`` of the data directory (``--data``, ``bench/_data.py``); SystemExit if missing."""
    return _data.needed("carmen")


def log_paths(folder: Path | None = None) -> list[Path]:
    """Every ``*.log.gz`` in ``folder`` (default ``log_dir()``), sorted; ``SystemExit`` with a message when there
    is none."""
    folder = log_dir() if folder is None else folder
    paths = sorted(folder.glob("*.log.gz"))
    if not paths:
        raise SystemExit(f"no CARMEN logs (*.log.gz) in {folder}: {_data.describe()}; give a data directory "
                         f"that holds carmen/*.log.gz with {_data.OPTION} DIR")
    return paths


def log_name(path: Path) -> str:
    return path.name.removesuffix(".log.gz").removesuffix("-corrected")


def grid_for(scans: list[LaserScan], resolution: float = RESOLUTION, margin: float = MARGIN_M) -> GridSpec:
    """The box of every pose and hit end point, padded by ``margin`` (what ``app.cli.import_log`` maps)."""
    return grid_for_scans(scans, resolution, margin)


@dataclass(frozen=True)
class HeldOut:
    """Held-out hit beams (a log's, or a 3-D sweep's): origins, unit directions and measured ranges."""

    origins: np.ndarray  # (N, D)
    directions: np.ndarray  # (N, D)
    ranges: np.ndarray  # (N,)


def split(scans: list[LaserScan], every: int = HOLDOUT_EVERY) -> tuple[list[LaserScan], list[LaserScan]]:
    """(fused, held out): scan ``i`` is held out when ``i % every == every - 1``."""
    fused = [s for i, s in enumerate(scans) if i % every != every - 1]
    held = [s for i, s in enumerate(scans) if i % every == every - 1]
    return fused, held


def held_out_beams(scans: list[LaserScan]) -> HeldOut:
    origins, dirs, ranges = [], [], []
    for s in scans:
        rays = s.to_rays()
        n = int(rays.hit.sum())
        origins.append(np.repeat(rays.origin[None, :], n, axis=0))
        dirs.append(rays.directions[rays.hit])
        ranges.append(rays.ranges[rays.hit])
    return HeldOut(np.concatenate(origins), np.concatenate(dirs), np.concatenate(ranges))


@njit(cache=True)
def _march(risk, lower, res, origins, dirs, threshold, out):  # pragma: no cover - compiled
    """Distance from each origin to the centre of the first cell at or above ``threshold`` (inf: none in the grid),
    by Amanatides-Woo over a 3-D grid (a 2-D map is one cell high, its rays level)."""
    nx, ny, nz = risk.shape
    for r in range(origins.shape[0]):
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        i = int(math.floor((ox - lower[0]) / res))
        j = int(math.floor((oy - lower[1]) / res))
        k = int(math.floor((oz - lower[2]) / res))
        out[r] = np.inf
        if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
            continue
        si = 1 if dx > 0 else -1
        sj = 1 if dy > 0 else -1
        sk = 1 if dz > 0 else -1
        tdx = abs(res / dx) if dx != 0.0 else np.inf
        tdy = abs(res / dy) if dy != 0.0 else np.inf
        tdz = abs(res / dz) if dz != 0.0 else np.inf
        tmx = (lower[0] + (i + (1 if dx > 0 else 0)) * res - ox) / dx if dx != 0.0 else np.inf
        tmy = (lower[1] + (j + (1 if dy > 0 else 0)) * res - oy) / dy if dy != 0.0 else np.inf
        tmz = (lower[2] + (k + (1 if dz > 0 else 0)) * res - oz) / dz if dz != 0.0 else np.inf
        while 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
            if risk[i, j, k] >= threshold:
                cx = lower[0] + (i + 0.5) * res - ox
                cy = lower[1] + (j + 0.5) * res - oy
                cz = lower[2] + (k + 0.5) * res - oz
                out[r] = math.sqrt(cx * cx + cy * cy + cz * cz)
                break
            if tmx < tmy and tmx < tmz:
                i += si
                tmx += tdx
            elif tmy <= tmz:
                j += sj
                tmy += tdy
            else:
                k += sk
                tmz += tdz


def predicted_ranges(risk: np.ndarray, spec: GridSpec | Window, beams: HeldOut,
                     threshold: float = OCCUPIED) -> np.ndarray:
    """Range each held-out beam reads off a 2-D or 3-D risk grid of ``spec``'s cells: the distance from its origin to
    the centre of the first cell at or above ``threshold`` (inf where it finds none before leaving the grid)."""
    out = np.empty(beams.ranges.size)
    origins, dirs = np.asarray(beams.origins, dtype=np.float64), np.asarray(beams.directions, dtype=np.float64)
    lower = np.asarray(spec.origin, dtype=np.float64)
    if risk.ndim == 2:  # one cell high, the beams at its centre's height and level
        risk = risk[:, :, None]
        lower = np.append(lower, 0.0)
        origins = np.column_stack([origins, np.full(len(origins), 0.5 * spec.resolution)])
        dirs = np.column_stack([dirs, np.zeros(len(dirs))])
    _march(np.ascontiguousarray(risk, dtype=np.float32), lower, spec.resolution, np.ascontiguousarray(origins),
           np.ascontiguousarray(dirs), float(threshold), out)
    return out


@dataclass(frozen=True)
class Score:
    """Held-out beam prediction figures of one map (fractions of the held-out hit beams)."""

    beams: int
    within: float
    early: float
    late: float
    none: float
    median_error: float  # metres, a beam with no surface counting as infinitely wrong

    def row(self) -> list[str]:
        med = "inf" if math.isinf(self.median_error) else f"{100 * self.median_error:.1f} cm"
        return [f"{100 * self.within:.1f} %", med, f"{100 * self.early:.1f} %", f"{100 * self.late:.1f} %",
                f"{100 * self.none:.1f} %"]


def score(predicted: np.ndarray, measured: np.ndarray, resolution: float = RESOLUTION) -> Score:
    tol = TOLERANCE_CELLS * resolution + 1e-9
    err = predicted - measured
    found = np.isfinite(predicted)
    n = max(1, measured.size)
    return Score(
        beams=int(measured.size),
        within=float(np.sum(found & (np.abs(err) <= tol)) / n),
        early=float(np.sum(found & (err < -tol)) / n),
        late=float(np.sum(found & (err > tol)) / n),
        none=float(np.sum(~found) / n),
        median_error=float(np.median(np.where(found, np.abs(err), np.inf))),
    )


def fuse(model: FuzzyMap | BayesMap, scans: list[LaserScan], batch: int = 16) -> None:
    """Fuse ``scans`` in order, a batch at a time (as a robot streams them to the service)."""
    for k in range(0, len(scans), batch):
        model.integrate_batch(scans[k : k + batch])


# -------------------------------------------------------------------- OctoMap
def _z(spec: GridSpec) -> float:
    return 0.5 * spec.resolution  # the centre of OctoMap's cell [0, res) in z


def octomap_tree(spec: GridSpec, scans: list[LaserScan]):  # type: ignore[no-untyped-def]
    """An OctoMap ``OcTree`` (default sensor model) of ``scans``, updates limited to the map's box."""
    import octomap  # the bench extra: octomap-python

    tree = octomap.OcTree(spec.resolution)
    z = _z(spec)
    tree.setBBXMin(np.array([spec.origin[0], spec.origin[1], 0.0]))
    tree.setBBXMax(np.array([spec.upper[0], spec.upper[1], spec.resolution * 0.999]))
    tree.useBBXLimit(True)
    reach = float(np.hypot(*np.subtract(spec.upper, spec.origin)))
    for s in scans:
        insert_scan(tree, s, z, reach)
    return tree


def insert_scan(tree, scan: LaserScan, z: float, reach: float) -> None:  # type: ignore[no-untyped-def]
    """One scan into an OcTree in one ``insertPointCloud`` (so its occupied-before-free rule holds
    across the whole scan): hits as end points, every no-return as a free beam cut at
    ``range_max`` (REP 117, as the paper engine clears it), or at ``reach`` (the map's diagonal)
    if that is shorter. Our default engine also shortens the no-returns that have hits beside
    them (``Rays.cut_no_returns``): a part of our model, so OctoMap gets the raw scan."""
    rays = scan.to_rays()
    origin = np.array([rays.origin[0], rays.origin[1], z])
    cut = min(reach, scan.range_max)  # every hit lies within it: below range_max, inside the map
    ends = rays.origin + rays.directions * np.where(rays.hit, rays.ranges, cut + 1.0)[:, None]
    if ends.size:
        tree.insertPointCloud(np.column_stack([ends, np.full(len(ends), z)]), origin, maxrange=cut)


def octomap_predicted(tree, spec: GridSpec, beams: HeldOut) -> np.ndarray:  # type: ignore[no-untyped-def]
    """``castRay`` of every held-out beam (unknown cells ignored) up to the map's box; inf where it hits nothing."""
    z = _z(spec)
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    o, d = beams.origins, beams.directions
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf)).min(axis=1)
    n = beams.ranges.size
    ends = octomap_ends(tree, np.column_stack([o, np.full(n, z)]), np.column_stack([d, np.zeros(n)]), reach)
    found = ~np.isnan(ends[:, 0])
    return np.where(found, np.hypot(ends[:, 0] - o[:, 0], ends[:, 1] - o[:, 1]), np.inf)


def octomap_ends(tree, origins: np.ndarray, directions: np.ndarray,  # type: ignore[no-untyped-def]
                 reach: np.ndarray | float) -> np.ndarray:
    """``castRay`` of each 3-D ray ((N, 3) origins and unit directions), unknown cells ignored, up to ``reach``
    metres (one for all or (N,)): the centre of the occupied cell it stops in, (N, 3), NaN where there is none."""
    reach = np.broadcast_to(np.asarray(reach, dtype=np.float64), (len(origins),))
    out = np.full((len(origins), 3), np.nan)
    end = np.zeros(3)
    for r in range(len(origins)):
        if tree.castRay(np.array(origins[r], dtype=np.float64), np.array(directions[r], dtype=np.float64), end,
                        ignoreUnknownCells=True, maxRange=float(reach[r])):
            out[r] = end
    return out


def octomap_occupied(tree, spec: GridSpec) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Boolean grid of ``spec.shape``: cells whose centre lies in an occupied OctoMap leaf."""
    occ = np.zeros(spec.shape, dtype=bool)
    res = spec.resolution
    for leaf in tree.begin_leafs():
        if not tree.isNodeOccupied(leaf):
            continue
        c, size = leaf.getCoordinate(), leaf.getSize()
        i0 = int(round((c[0] - size / 2 - spec.origin[0]) / res))
        j0 = int(round((c[1] - size / 2 - spec.origin[1]) / res))
        n = max(1, int(round(size / res)))
        occ[max(i0, 0) : max(i0 + n, 0), max(j0, 0) : max(j0 + n, 0)] = True
    return occ


def load(path: Path) -> list[LaserScan]:
    return read_carmen(path)
