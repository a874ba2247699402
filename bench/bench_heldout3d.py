"""3-D held-out ray quality on the real Ouster frames, ours beside OctoMap: the quality gate for fusion shortcuts.

    python3 dev.py bench heldout3d [--quick] [--data DIR]
    python -m bench.bench_heldout3d ...                                (from the repository root)

The three frames of an Ouster OS-1-128 in ``ouster/`` of the data directory (``bench_extent.ouster_clouds``: rows
at the origin dropped, ``range_max`` 30 m, every height), in three folds: fold k holds frame k out and fuses the
other two, in order, a frame a call, at each resolution (0.1 and 0.2 m) into

- ours: a growing map, default engine (``bench_extent.fuse_clouds``: ``FuzzyMap(LatticeSpec(3, res))``);
- OctoMap: an ``OcTree`` of the same resolution, default sensor model, each frame by ``insertPointCloud`` with its
  origin and ``maxrange`` 30 m (``bench_extent.octomap_of_clouds``).

The held-out rays: every ``STRIDE``-th return of frame k, in the frame's order, nearer its sensor than
``range_max`` (every ``QUICK_STRIDE``-th with ``--quick``). Each ray is cast from the held-out sensor origin
through both maps: ours by Amanatides-Woo through its risk (``_logmaps.predicted_ranges``) to the first cell of
risk > 0.5, OctoMap by ``castRay`` (unknown cells ignored) to its first occupied cell (``_logmaps.octomap_ends``);
the predicted range is the distance to that cell's centre, and nothing within ``REACH_M``: no surface. Scored as
``bench maps`` scores its 2-D beams (``_logmaps.score``): within 2 cells of the measured range, early, late, no
surface, and the median absolute error (a ray with no surface counts as infinitely wrong).

Printed: one row per fold and resolution, with the mean over the folds; then each fold's fusion time, ours
against OctoMap's, wall and CPU seconds (ours may split a cast between the cores, ``fuzzyocc.parallel``, as the
service does; OctoMap runs on one), a side figure. Before anything is timed, one frame is fused and cast at the
coarsest resolution to compile the kernels.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from bench import _data, _logmaps, bench_extent
from bench._client import machine
from bench._logmaps import HeldOut, Score
from bench.bench_fusion import Clock
from fuzzyocc import FuzzyMap, PointCloud
from fuzzyocc.grid import RISK_STEP

RESOLUTIONS = (0.1, 0.2)
QUICK_RESOLUTIONS = (0.2,)
STRIDE = 5  # about 19 k of a frame's 94 k returns within range_max: OctoMap's castRay is a Python call a ray
QUICK_STRIDE = 50
#: Ours: a cell is a surface above risk 0.5, as OctoMap's occupied is above probability 0.5 (risk is a multiple of
#: RISK_STEP, so this threshold of ``predicted_ranges``, which takes ``>=``, is ``> 0.5``).
OCCUPIED = 0.5 + RISK_STEP
#: Neither map holds anything farther from a held-out origin than ``range_max`` plus the 0.75 m the sensor moves
#: over the three frames; casts stop here (OctoMap's ``castRay`` ignoring unknown cells would walk on to the edge
#: of its tree), and a surface beyond it counts as none for both maps.
REACH_M = bench_extent.OUSTER_RANGE_MAX + 2.0


@dataclass(frozen=True)
class Fold:
    """One fold: frame ``held`` held out, the others fused in order."""

    held: int
    fused: list[PointCloud]
    held_out: PointCloud


@dataclass(frozen=True)
class FoldResult:
    """One fold at one resolution: both maps' scores and fusion times."""

    fold: int
    resolution: float
    ours: Score
    octomap: Score
    ours_clock: Clock
    octomap_clock: Clock


def folds(clouds: list[PointCloud]) -> list[Fold]:
    """Fold k holds cloud k out and fuses the others, in their order."""
    return [Fold(k, [c for i, c in enumerate(clouds) if i != k], clouds[k]) for k in range(len(clouds))]


def held_out_rays(cloud: PointCloud, stride: int) -> HeldOut:
    """Every ``stride``-th return of ``cloud`` (in its order) nearer its origin than its ``range_max``, as rays from
    the origin: unit directions and measured ranges."""
    origin = np.asarray(cloud.origin, dtype=np.float64)
    offsets = np.asarray(cloud.points, dtype=np.float64) - origin
    ranges = np.linalg.norm(offsets, axis=1)
    kept = np.flatnonzero((ranges > 0.0) & (ranges < cloud.range_max))[::stride]
    return HeldOut(np.repeat(origin[None, :], kept.size, axis=0), offsets[kept] / ranges[kept, None], ranges[kept])


def _within_reach(predicted: np.ndarray, reach: float) -> np.ndarray:
    return np.where(predicted <= reach, predicted, np.inf)


def our_ranges(m: FuzzyMap, rays: HeldOut, reach: float = REACH_M) -> np.ndarray:
    """The range each ray reads off our map: the centre of the first cell of risk > 0.5 within ``reach`` (inf:
    none). Marches the map's risk over the cells within ``reach`` of the rays' origins (beyond its bounds, nothing
    is observed)."""
    window = m.window(rays.origins.min(axis=0) - reach, rays.origins.max(axis=0) + reach)
    if window is None:
        return np.full(rays.ranges.size, np.inf)
    return _within_reach(_logmaps.predicted_ranges(m.risk(window), window, rays, OCCUPIED), reach)


def octomap_ranges(tree, rays: HeldOut, reach: float = REACH_M) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The range each ray reads off an OctoMap tree: ``castRay`` to its first occupied cell's centre within
    ``reach`` (inf: none)."""
    ends = _logmaps.octomap_ends(tree, rays.origins, rays.directions, reach)
    found = ~np.isnan(ends[:, 0])
    return _within_reach(np.where(found, np.linalg.norm(ends - rays.origins, axis=1), np.inf), reach)


def run_fold(fold: Fold, resolution: float, rays: HeldOut) -> FoldResult:
    """Both maps of ``fold``'s fused frames at ``resolution``, scored on ``rays``."""
    ours, ours_clock = bench_extent.fuse_clouds(fold.fused, resolution)
    ours_score = _logmaps.score(our_ranges(ours, rays), rays.ranges, resolution)
    del ours  # one map in memory at a time: ours at 0.1 m holds a few hundred MB
    tree, octomap_clock = bench_extent.octomap_of_clouds(fold.fused, resolution)
    octomap_score = _logmaps.score(octomap_ranges(tree, rays), rays.ranges, resolution)
    return FoldResult(fold.held, resolution, ours_score, octomap_score, ours_clock, octomap_clock)


def mean_score(scores: list[Score]) -> Score:
    """The mean of ``scores`` (each fraction and the median error; its rays: their sum)."""
    return Score(beams=sum(s.beams for s in scores),
                 within=float(np.mean([s.within for s in scores])),
                 early=float(np.mean([s.early for s in scores])),
                 late=float(np.mean([s.late for s in scores])),
                 none=float(np.mean([s.none for s in scores])),
                 median_error=float(np.mean([s.median_error for s in scores])))


def _cells(s: Score) -> str:
    median = "inf" if math.isinf(s.median_error) else f"{100 * s.median_error:.1f} cm"
    return (f"{100 * s.within:6.1f} % {100 * s.early:6.1f} % {100 * s.late:6.1f} % {100 * s.none:6.1f} % "
            f"{median:>9s}")


def print_table(results: list[FoldResult]) -> None:
    """The quality table: a row per fold and resolution, then the mean over the folds of each resolution."""
    score_head = f"{'within':>8s} {'early':>8s} {'late':>8s} {'none':>8s} {'median':>9s}"
    print(f"\n{'fold':>4s} {'res m':>5s} {'rays':>7s} | ours: {score_head} | OctoMap: {score_head}")
    for res in sorted({r.resolution for r in results}):
        at = [r for r in results if r.resolution == res]
        for r in at:
            print(f"{r.fold:4d} {res:5.2f} {r.ours.beams:7,} |       {_cells(r.ours)} |          {_cells(r.octomap)}")
        ours, theirs = mean_score([r.ours for r in at]), mean_score([r.octomap for r in at])
        print(f"{'mean':>4s} {res:5.2f} {ours.beams:7,} |       {_cells(ours)} |          {_cells(theirs)}")
        better = sum(r.ours.within >= r.octomap.within for r in at)
        print(f"  at {res} m, within 2 cells: ours {100 * ours.within:.1f} %, OctoMap {100 * theirs.within:.1f} % "
              f"(mean of the folds); ours >= OctoMap's on {better} of {len(at)} folds"
              f"{'' if better == len(at) else ': ours is WORSE on the others'}")


def print_times(results: list[FoldResult]) -> None:
    """The side figure: each fold's fusion of its two frames, ours against OctoMap's."""
    print(f"\nfusion of the two frames of each fold (side figure): wall / CPU seconds\n"
          f"{'fold':>4s} {'res m':>5s} {'ours wall':>10s} {'ours cpu':>9s} {'OctoMap wall':>13s} {'OctoMap cpu':>12s} "
          f"{'OctoMap / ours, wall':>21s} {'by cpu':>7s}")
    for r in results:
        o, t = r.ours_clock, r.octomap_clock
        print(f"{r.fold:4d} {r.resolution:5.2f} {o.wall:10.2f} {o.cpu:9.2f} {t.wall:13.2f} {t.cpu:12.2f} "
              f"{t.wall / o.wall:20.1f}x {t.cpu / o.cpu:6.1f}x")


def _warm_up(cloud: PointCloud, resolution: float) -> None:
    """Compile (or load) our fusion's and the march's kernels before anything is timed: a whole frame, as a big
    cloud takes paths (its cast split between threads) that a small one does not."""
    m, _ = bench_extent.fuse_clouds([cloud], resolution)
    our_ranges(m, held_out_rays(cloud, QUICK_STRIDE))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench heldout3d", description=__doc__.split("\n\n")[0])
    _data.add_option(ap)
    ap.add_argument("--quick", action="store_true",
                    help=f"at {', '.join(map(str, QUICK_RESOLUTIONS))} m only, every {QUICK_STRIDE}th return held "
                         f"out (default: {', '.join(map(str, RESOLUTIONS))} m, every {STRIDE}th)")
    args = ap.parse_args(argv)
    _data.use(args)
    folder = _data.needed("ouster")  # before any work: a missing folder ends the run
    resolutions, stride = (QUICK_RESOLUTIONS, QUICK_STRIDE) if args.quick else (RESOLUTIONS, STRIDE)
    started = time.perf_counter()
    print(f"# bench heldout3d, {datetime.now().astimezone():%Y-%m-%d %H:%M %Z}; {machine()}")
    clouds = bench_extent.ouster_clouds(folder)
    print(f"{len(clouds)} Ouster frames from {folder} ({', '.join(f'{c.points.shape[0]:,}' for c in clouds)} "
          f"returns), range_max {bench_extent.OUSTER_RANGE_MAX:g} m, every height; held out: every {stride}th return "
          f"within range_max; surface: ours risk > 0.5, OctoMap occupied; casts reach {REACH_M:g} m; within = "
          f"|error| <= {_logmaps.TOLERANCE_CELLS} cells")
    t0 = time.perf_counter()
    _warm_up(clouds[0], max(resolutions))
    print(f"numba warm-up: {time.perf_counter() - t0:.1f} s (excluded from the times below)", flush=True)
    results = []
    for fold in folds(clouds):
        rays = held_out_rays(fold.held_out, stride)
        for res in resolutions:
            results.append(run_fold(fold, res, rays))
            r = results[-1]
            print(f"  fold {fold.held} at {res} m: {rays.ranges.size:,} rays, within 2 cells ours "
                  f"{100 * r.ours.within:.1f} %, OctoMap {100 * r.octomap.within:.1f} %", flush=True)
    print_table(results)
    print_times(results)
    print(f"\n{time.perf_counter() - started:.0f} s in all; {machine()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
