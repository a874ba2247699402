"""The planner's hand-written kernels against the scipy calls they stand for, same inputs, same run.

    python3 dev.py bench kernels [--size N] [--repeat N]

- **box maximum**: ``planning.field.box_max`` against ``scipy.ndimage.maximum_filter`` (one 9 x 9 box,
  float32), bit for bit;
- **dilation by the robot**: what ``RiskField.dilated_risk`` runs at the default 0.2 m radius on a 0.05 m
  grid, against the same union of boxes with ``maximum_filter`` and against ``grey_dilation`` with the
  footprint;
- **erosion** of the packed grid's validity (3 x 3): ``box_max`` of the invalid cells against
  ``ndimage.minimum_filter``;
- **grid search**: ``planning.grid_search.grid_path`` (A*) against ``scipy.sparse.csgraph.dijkstra``
  on the same cell graph, corner to corner (the graph's construction timed apart).

Each time is the best of ``--repeat`` runs, ours and scipy's alternating. docs/DESIGN.md section 11
quotes the ratios.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from planning.field import RiskField, _boxes, _dilate_max, box_max, footprint
from planning.grid_search import grid_path
from planning.packed import PackedGrid

RESOLUTION = 0.05
ROBOT_RADIUS = 0.2


def _best(repeat: int, *runs: Callable[[], Any]) -> list[float]:
    """Best wall time of each run over ``repeat`` alternating rounds (each run once before, to compile)."""
    for run in runs:
        run()
    best = [math.inf] * len(runs)
    for _ in range(repeat):
        for k, run in enumerate(runs):
            started = time.perf_counter()
            run()
            best[k] = min(best[k], time.perf_counter() - started)
    return best


def _row(what: str, ours: float, peer_name: str, peer: float) -> None:
    print(f"| {what} | {ours * 1e3:,.1f} ms | {peer_name} {peer * 1e3:,.1f} ms | **{peer / ours:.1f}x** |", flush=True)


def _risk(size: int, rng: np.random.Generator) -> np.ndarray:
    # quantised as maps are, with walls of risk 1 and unknown space at 0.5
    risk = (np.round(rng.random((size, size)) ** 4 * 2**16) / 2**16).astype(np.float32)
    risk[rng.random((size, size)) < 0.02] = 1.0
    return risk


def _scipy_dilation(values: np.ndarray, fp: np.ndarray, outside: float) -> np.ndarray:
    out = None
    for half in _boxes(fp):
        part = ndimage.maximum_filter(values, size=tuple(2 * h + 1 for h in half), mode="constant", cval=outside)
        out = part if out is None else np.maximum(out, part)
    assert out is not None
    return out


def _cell_graph(risk: np.ndarray, valid: np.ndarray, weight: float) -> sparse.csr_matrix:
    """The grid planner's graph: 8 neighbours, edge ``|ab| (1 + w (r_a + r_b) / 2)`` between valid cells."""
    n, m = risk.shape
    r = risk.astype(np.float64).ravel()
    ok_cells = valid.ravel()
    index = np.arange(n * m).reshape(n, m)
    rows, cols, weights = [], [], []
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        j0, j1 = max(0, -dj), m - max(0, dj)
        a = index[0 : n - di, j0:j1].ravel()
        b = index[di:n, j0 + dj : j1 + dj].ravel()
        ok = ok_cells[a] & ok_cells[b]
        rows.append(a[ok])
        cols.append(b[ok])
        weights.append(RESOLUTION * math.hypot(di, dj) * (1.0 + weight * 0.5 * (r[a[ok]] + r[b[ok]])))
    coo = sparse.coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n * m,) * 2)
    return coo.tocsr()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4000, help="cells along each side of the grids (default 4000)")
    ap.add_argument("--search-size", type=int, default=1000, help="cells along each side for the grid search")
    ap.add_argument("--repeat", type=int, default=5, help="rounds; the best of each is printed (default 5)")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    risk = _risk(args.size, rng)
    print(f"{args.size} x {args.size} grid at {RESOLUTION} m, robot radius {ROBOT_RADIUS} m; best of {args.repeat}")
    print("| kernel | ours | scipy | scipy / ours |")
    print("|---|---|---|---|")

    half = (4, 4)
    assert np.array_equal(box_max(risk, half, 0.5), ndimage.maximum_filter(risk, size=9, mode="constant", cval=0.5))
    ours, peer = _best(args.repeat, lambda: box_max(risk, half, 0.5),
                       lambda: ndimage.maximum_filter(risk, size=9, mode="constant", cval=0.5))
    _row("box maximum, 9 x 9, float32", ours, "`maximum_filter`", peer)

    fp = footprint(ROBOT_RADIUS, RESOLUTION, 2)
    field = RiskField(risk, RESOLUTION, (0.0, 0.0))
    assert np.array_equal(field.dilated_risk(ROBOT_RADIUS), _scipy_dilation(risk, fp, 0.5))
    # what RiskField.dilated_risk runs (a field caches its dilation per radius, and checks its risk when made)
    ours, peer, generic = _best(
        args.repeat, lambda: _dilate_max(risk, fp, 0.5), lambda: _scipy_dilation(risk, fp, 0.5),
        lambda: ndimage.grey_dilation(risk, footprint=fp, mode="constant", cval=0.5))
    _row(f"dilation by the robot ({len(_boxes(fp))} boxes)", ours, "`maximum_filter` per box", peer)
    _row("dilation by the robot", ours, "`grey_dilation` with the footprint", generic)

    valid = risk <= 0.45
    invalid = (~valid).view(np.uint8)
    assert np.array_equal(box_max(invalid, (1, 1), 1) == 0, ndimage.minimum_filter(valid, size=3, mode="constant",
                                                                                      cval=False))
    ours, peer = _best(args.repeat, lambda: box_max(invalid, (1, 1), 1),
                       lambda: ndimage.minimum_filter(valid, size=3, mode="constant", cval=False))
    _row("erosion of validity, 3 x 3", ours, "`minimum_filter`", peer)

    n = args.search_size
    small = risk[:n, :n].copy()
    small[0, 0] = small[-1, -1] = 0.0
    grid = PackedGrid(RiskField(small, RESOLUTION, (0.0, 0.0)), 0.0, 0.45, True, 1.0)
    start, goal = (0.5 * RESOLUTION,) * 2, ((n - 0.5) * RESOLUTION,) * 2
    found = grid_path(grid, start, goal)
    graph = _cell_graph(small, grid.valid, 1.0)
    dist = csgraph.dijkstra(graph, directed=False, indices=0)
    assert found.reached and math.isclose(found.graph_cost, dist[n * n - 1], rel_tol=1e-9)
    ours, peer, build = _best(args.repeat, lambda: grid_path(grid, start, goal),
                              lambda: csgraph.dijkstra(graph, directed=False, indices=0),
                              lambda: _cell_graph(small, grid.valid, 1.0))
    _row(f"grid search corner to corner, {n} x {n}", ours, "`csgraph.dijkstra`", peer)
    _row(f"grid search corner to corner, {n} x {n}", ours, "the graph built + `csgraph.dijkstra`", peer + build)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
