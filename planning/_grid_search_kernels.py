"""Compiled A* over the cells of a packed risk grid (the grid planner, and the seed of sampling plans)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from planning._segment_kernels import H_INV_RES, H_NCELLS, H_RISK_FLOOR, H_SHAPE, H_WEIGHT

_CLOSED = -2  # grid_search: pos of an expanded cell


@njit(cache=True, inline="always")
def _heap_up(keys: np.ndarray, nodes: np.ndarray, pos: np.ndarray, h: int) -> None:
    key = keys[h]
    node = nodes[h]
    while h > 0:
        parent = (h - 1) >> 1
        if keys[parent] <= key:
            break
        keys[h] = keys[parent]
        nodes[h] = nodes[parent]
        pos[nodes[h]] = h
        h = parent
    keys[h] = key
    nodes[h] = node
    pos[node] = h


@njit(cache=True, inline="always")
def _heap_down(keys: np.ndarray, nodes: np.ndarray, pos: np.ndarray, size: int) -> None:
    key = keys[0]
    node = nodes[0]
    h = 0
    while True:
        c = 2 * h + 1
        if c >= size:
            break
        if c + 1 < size and keys[c + 1] < keys[c]:
            c += 1
        if keys[c] >= key:
            break
        keys[h] = keys[c]
        nodes[h] = nodes[c]
        pos[nodes[h]] = h
        h = c
    keys[h] = key
    nodes[h] = node
    pos[node] = h


@njit(cache=True, inline="always")
def _octile(a0: int, a1: int, a2: int, b0: int, b1: int, b2: int) -> float:
    """Shortest 26-connected (8 in a plane) step length between two cells, in cells."""
    d0 = abs(a0 - b0)
    d1 = abs(a1 - b1)
    d2 = abs(a2 - b2)
    hi = max(d0, d1, d2)
    lo = min(d0, d1, d2)
    mid = d0 + d1 + d2 - hi - lo
    return (hi - mid) + math.sqrt(2.0) * (mid - lo) + math.sqrt(3.0) * lo


@njit(cache=True)
def grid_search(
    buf: np.ndarray,
    risk: np.ndarray,
    valid: np.ndarray,
    start: int,
    goal: int,
    parent: np.ndarray,
    pos: np.ndarray,
    keys: np.ndarray,
    nodes: np.ndarray,
    max_expansions: int,
) -> tuple[np.ndarray, bool, float]:
    """A* over valid cells, 8-connected in a plane and 26-connected in 3-D.

    An edge between neighbouring cells a and b costs ``|ab| (1 + w (r_a + r_b) / 2)``,
    which is exactly the risk integral of the straight segment between their centres
    (half of it lies in each cell). The octile distance times the resolution times
    ``1 + w * floor`` (``floor`` the least risk of any cell) is a consistent heuristic
    because every edge costs at least that much per metre (on a building's map free space is
    at risk 0.033, not 0: the floor saves a tenth of the expansions).

    ``buf`` gives the header (shape, resolution, weight, risk floor); ``risk`` (float32) and
    ``valid`` (bool) are the packed grid's own flat arrays, read instead of the buffer's
    float64 copies: a quarter of the bytes per neighbour for the validity test, half for the
    risk. ``parent``, ``pos``, ``nodes`` (int32) and ``keys`` (float64) are scratch arrays of
    one entry per cell, left uninitialised: :func:`planning.grid_search.grid_path` makes them
    with NumPy's ``empty``, which does not write them (numba's fills every new array with a
    debug pattern: 9 ms for four of them on a 2 M-cell map, more than most searches take).

    ``max_expansions`` > 0 ends the search after that many expansions, as if the goal were
    unreachable (the bound of a grid seed's time); -1 searches to the end.

    Returns (cell indices from ``start`` to the goal, or to the reached cell nearest to
    it when the goal is unreachable; reached the goal; cost of that cell chain).
    """
    nx = int(buf[H_SHAPE])
    ny = int(buf[H_SHAPE + 1])
    nz = int(buf[H_SHAPE + 2])
    n = int(buf[H_NCELLS])
    res = 1.0 / buf[H_INV_RES]
    w = buf[H_WEIGHT]
    h_scale = res * (1.0 + w * buf[H_RISK_FLOOR])

    # neighbour offsets: in-plane only when the grid is one cell deep
    zr = 1 if nz > 1 else 0
    m = 0
    off_i = np.empty(26, dtype=np.int64)
    off_j = np.empty(26, dtype=np.int64)
    off_k = np.empty(26, dtype=np.int64)
    off_len = np.empty(26)
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-zr, zr + 1):
                if a == 0 and b == 0 and c == 0:
                    continue
                off_i[m] = a
                off_j[m] = b
                off_k[m] = c
                off_len[m] = res * math.sqrt(a * a + b * b + c * c)
                m += 1

    # Only g is filled up front. The scratch arrays are read only at cells whose g is finite
    # (seen), so their untouched pages are never faulted in: a search costs memory in proportion
    # to what it explores, not to the map. pos is a seen cell's heap slot, CLOSED once expanded.
    g = np.full(n, np.inf)
    gk = goal % nz
    gj = (goal // nz) % ny
    gi = goal // (nz * ny)

    size = 0
    g[start] = 0.0
    parent[start] = -1
    sk = start % nz
    sj = (start // nz) % ny
    si = start // (nz * ny)
    keys[0] = h_scale * _octile(si, sj, sk, gi, gj, gk)
    nodes[0] = start
    pos[start] = 0
    size = 1
    best = start
    best_h = np.inf  # squared distance in cells from the goal of the nearest expanded cell
    reached = False
    expansions = 0
    while size > 0:
        if expansions == max_expansions:
            break
        expansions += 1
        c = nodes[0]
        size -= 1
        pos[c] = _CLOSED
        if size > 0:
            keys[0] = keys[size]
            nodes[0] = nodes[size]
            pos[nodes[0]] = 0
            _heap_down(keys, nodes, pos, size)
        if c == goal:
            reached = True
            best = c
            break
        if nz == 1:  # a plane: one division instead of three
            ci = c // ny
            cj = c - ci * ny
            ck = 0
        else:
            ck = c % nz
            cj = (c // nz) % ny
            ci = c // (nz * ny)
        hc = (ci - gi) ** 2 + (cj - gj) ** 2 + (ck - gk) ** 2
        if hc < best_h:
            best_h = hc
            best = c
        rc = np.float64(risk[c])  # float64 sums, as the cost of a path is measured
        for e in range(m):
            ni = ci + off_i[e]
            nj = cj + off_j[e]
            nk = ck + off_k[e]
            if ni < 0 or ni >= nx or nj < 0 or nj >= ny or nk < 0 or nk >= nz:
                continue
            nb = (ni * ny + nj) * nz + nk
            gn = g[nb]
            seen = gn < np.inf
            if (seen and pos[nb] == _CLOSED) or not valid[nb]:
                continue
            ng = g[c] + off_len[e] * (1.0 + w * 0.5 * (rc + np.float64(risk[nb])))
            if ng < gn:
                g[nb] = ng
                parent[nb] = c
                f = ng + h_scale * _octile(ni, nj, nk, gi, gj, gk)
                if not seen:
                    keys[size] = f
                    nodes[size] = nb
                    pos[nb] = size
                    size += 1
                    _heap_up(keys, nodes, pos, size - 1)
                else:
                    keys[pos[nb]] = f
                    _heap_up(keys, nodes, pos, pos[nb])
    # the chain back from the end cell
    length = 0
    c = best
    while c >= 0:
        length += 1
        c = parent[c]
    chain = np.empty(length, dtype=np.int64)
    c = best
    for s in range(length - 1, -1, -1):
        chain[s] = c
        c = parent[c]
    return chain, reached, g[best]
