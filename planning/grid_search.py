"""The grid planner: A* over the cell graph with the same cost as every other planner.

8-connected in the plane, 26-connected in 3-D; an edge between neighbouring valid cells
costs ``|ab| (1 + w (r_a + r_b) / 2)``, the exact risk integral of the segment between
their centres. It is a planner users can pick and the yardstick of path quality: its cost
is optimal over the cell graph (any-angle paths can be up to ~8 % shorter in free space,
which the shortcut that follows recovers in part).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planning import _grid_search_kernels
from planning.packed import PackedGrid


@dataclass(frozen=True)
class GridPath:
    reached: bool
    positions: np.ndarray  # (K, ndim): start, cell centres, goal (or the last centre)
    graph_cost: float  # cost of the cell chain alone, as the search summed it


def grid_path(
    grid: PackedGrid, start: tuple[float, ...], goal: tuple[float, ...], max_expansions: int | None = None
) -> GridPath:
    """Cheapest chain of valid cells from the start's cell to the goal's.

    Start and goal must lie in valid cells (``plan`` checks them first). When the goal is
    unreachable, or not reached within ``max_expansions`` expanded cells, the chain ends at
    the expanded cell nearest to it (an approximate path).
    """
    s = grid.cell_index(start)
    g = grid.cell_index(goal)
    assert s is not None and g is not None
    n = grid.valid.size
    index = np.int32 if n < 2**31 else np.int64  # half the bytes the search touches per cell
    parent, pos, nodes = (np.empty(n, dtype=index) for _ in range(3))  # never written here
    chain, reached, graph_cost = _grid_search_kernels.grid_search(
        grid.buffer, grid.risk.reshape(-1), grid.valid.reshape(-1), s, g, parent, pos, np.empty(n), nodes,
        -1 if max_expansions is None else max(1, int(max_expansions)),
    )
    cells = np.stack(np.unravel_index(chain, grid.shape), axis=1)
    centres = np.asarray(grid.origin) + (cells + 0.5) * grid.resolution
    # the start (goal) and its cell's centre share one convex valid cell: the joins are valid
    parts = [np.asarray(start, dtype=np.float64)[None, :], centres]
    if reached:
        parts.append(np.asarray(goal, dtype=np.float64)[None, :])
    return GridPath(bool(reached), np.concatenate(parts), float(graph_cost))
