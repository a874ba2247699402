"""Compiled kernels over a packed risk grid: segment cost and validity, grid search, shortcuts.

Everything the planners call per edge lives here, compiled by numba, because the
objective and the motion validator are called from C++ for every edge and their
cost per call is the planner's speed (``notes/ompl-2.0-python.md``).

The grid is packed once per query into one contiguous float64 buffer (see
:func:`pack`), so a hot kernel takes one integer (the buffer's address) and the
segment's coordinates: numba unboxes scalars much faster than arrays, which is
most of the price of a call from Python.

Segments are walked cell by cell (Amanatides & Woo, "A fast voxel traversal
algorithm for ray tracing", 1987) in grid units ``u = (p - origin) / resolution``:
the walk visits every cell in which the segment has positive length, so the risk
integral is exact for the piecewise-constant field and the validity check misses no
cell however thin. A 2-D grid is packed as a 3-D grid one cell deep.
"""

from __future__ import annotations

import math

import numpy as np
from numba import carray, njit, types
from numba.extending import intrinsic

# header of the packed buffer; the risk block follows it, then the valid block
H_ORIGIN = 0  # 3 slots: origin x, y, z (metres)
H_INV_RES = 3  # 1 / resolution
H_SHAPE = 4  # 3 slots: nx, ny, nz
H_NCELLS = 7
H_WEIGHT = 8  # risk_weight
H_RHO = 9  # Dubins turning radius (metres), 0 when unused
H_RISK_FLOOR = 10  # least risk of any cell: every motion costs at least its length x (1 + weight x this)
HEADER = 16


@intrinsic
def _f64_ptr(typingctx, address):  # type: ignore[no-untyped-def]
    """Reinterpret an integer address as ``double*`` (the owner keeps the buffer alive)."""
    sig = types.CPointer(types.float64)(types.intp)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.float64)))

    return sig, codegen


def pack(
    risk: np.ndarray,
    valid: np.ndarray,
    origin: tuple[float, ...],
    resolution: float,
    risk_weight: float,
    turning_radius: float = 0.0,
) -> np.ndarray:
    """Pack a (dilated) risk grid and its validity mask into one float64 buffer.

    Parameters
    ----------
    risk : (nx, ny) or (nx, ny, nz) float array
        Risk per cell, indexed along x, y(, z).
    valid : bool array, same shape
        Cells in which every point is a valid robot position.
    origin : tuple of float
        Corner of cell 0 (metres).
    resolution : float
        Cell size (metres).
    risk_weight : float
        Weight of the risk integral in the cost.
    turning_radius : float
        Of Dubins motions (metres); 0 when unused.

    Returns
    -------
    (16 + 2 N,) float64 array
        Header, then risk in C order, then valid as 0.0 / 1.0.
    """
    shape = tuple(risk.shape) + (1,) * (3 - risk.ndim)
    org = tuple(float(v) for v in origin) + (0.0,) * (3 - len(origin))
    n = int(np.prod(shape))
    buf = np.zeros(HEADER + 2 * n, dtype=np.float64)
    buf[H_ORIGIN : H_ORIGIN + 3] = org
    buf[H_INV_RES] = 1.0 / resolution
    buf[H_SHAPE : H_SHAPE + 3] = shape
    buf[H_NCELLS] = n
    buf[H_WEIGHT] = risk_weight
    buf[H_RHO] = turning_radius
    buf[H_RISK_FLOOR] = max(0.0, float(risk.min())) if n else 0.0
    buf[HEADER : HEADER + n] = risk.reshape(-1)
    buf[HEADER + n :] = valid.reshape(-1)
    return buf


@njit(cache=True, inline="always")
def _axis_setup(u: float, du: float) -> tuple[int, int, float, float]:
    """Start cell, step, parameter of the first boundary crossing, parameter per cell."""
    c = int(math.floor(u))
    if du > 0.0:
        return c, 1, (c + 1.0 - u) / du, 1.0 / du
    if du < 0.0:
        return c, -1, (c - u) / du, -1.0 / du
    return c, 0, math.inf, math.inf


# pieces shorter than this (in cells) are corner touches made inexact by rounding
CORNER_EPS_CELLS = 1e-9


@njit(cache=True, inline="always")
def _eps_t(length_cells: float) -> float:
    """Parameter span of CORNER_EPS_CELLS along a segment; a degenerate segment checks its cell."""
    if length_cells <= 0.0:
        return -1.0
    return min(CORNER_EPS_CELLS / length_cells, 0.5)


@njit(cache=True)
def _walk(
    buf: np.ndarray, x1: float, y1: float, z1: float, x2: float, y2: float, z2: float, stop_on_invalid: bool
) -> tuple[float, float, bool]:
    """Walk a segment cell by cell.

    Returns (integral of risk over the segment parameter t in [0, 1], max risk met,
    every cell valid). Multiply the integral by the length for metres x risk. An
    endpoint outside the grid makes the segment invalid.
    """
    inv = buf[H_INV_RES]
    nx = int(buf[H_SHAPE])
    ny = int(buf[H_SHAPE + 1])
    nz = int(buf[H_SHAPE + 2])
    n = int(buf[H_NCELLS])
    u1 = (x1 - buf[H_ORIGIN]) * inv
    v1 = (y1 - buf[H_ORIGIN + 1]) * inv
    w1 = (z1 - buf[H_ORIGIN + 2]) * inv
    u2 = (x2 - buf[H_ORIGIN]) * inv
    v2 = (y2 - buf[H_ORIGIN + 1]) * inv
    w2 = (z2 - buf[H_ORIGIN + 2]) * inv
    if not (0.0 <= u1 < nx and 0.0 <= v1 < ny and 0.0 <= w1 < nz):
        return 0.0, 1.0, False
    if not (0.0 <= u2 < nx and 0.0 <= v2 < ny and 0.0 <= w2 < nz):
        return 0.0, 1.0, False
    i, si, ti, di = _axis_setup(u1, u2 - u1)
    j, sj, tj, dj = _axis_setup(v1, v2 - v1)
    k, sk, tk, dk = _axis_setup(w1, w2 - w1)
    steps = abs(int(math.floor(u2)) - i) + abs(int(math.floor(v2)) - j) + abs(int(math.floor(w2)) - k) + 1
    eps_t = _eps_t(math.sqrt((u2 - u1) ** 2 + (v2 - v1) ** 2 + (w2 - w1) ** 2))
    t = 0.0
    acc = 0.0
    peak = 0.0
    ok = True
    for _ in range(steps + 1):
        # rounding can carry a walk one cell past the grid on its boundary: clamp, never wrap
        idx = (min(max(i, 0), nx - 1) * ny + min(max(j, 0), ny - 1)) * nz + min(max(k, 0), nz - 1)
        r = buf[HEADER + idx]
        t_next = min(ti, tj, tk, 1.0)
        # a cell met for (next to) zero length, the segment through a corner, is not checked:
        # every point lies in the closure of a cell crossed for positive length, and the
        # dilation bounds the footprint over each closed cell (see field.py)
        if t_next - t > eps_t:
            if r > peak:
                peak = r
            if buf[HEADER + n + idx] == 0.0:
                ok = False
                if stop_on_invalid:
                    return acc, peak, False
            acc += r * (t_next - t)
        if t_next >= 1.0:
            break
        t = t_next
        if ti <= tj and ti <= tk:
            i += si
            ti += di
        elif tj <= tk:
            j += sj
            tj += dj
        else:
            k += sk
            tk += dk
    return acc, peak, ok


# ---------------------------------------------------------------- hot entry points
# One address and the coordinates, nothing else to unbox. The 2-D pair is written out
# by hand (no z axis, no validity block read in the cost) because it is the common case.


@njit("float64(intp, float64, float64, float64, float64)", cache=True)
def segment_cost_2d(address: int, x1: float, y1: float, x2: float, y2: float) -> float:
    """Cost ``length * (1 + w * mean risk)`` of a straight segment in a packed 2-D grid."""
    ptr = _f64_ptr(address)
    inv = ptr[H_INV_RES]
    ox = ptr[H_ORIGIN]
    oy = ptr[H_ORIGIN + 1]
    nx = int(ptr[H_SHAPE])
    ny = int(ptr[H_SHAPE + 1])
    dx = x2 - x1
    dy = y2 - y1
    u1 = (x1 - ox) * inv
    v1 = (y1 - oy) * inv
    u2 = (x2 - ox) * inv
    v2 = (y2 - oy) * inv
    i, si, ti, di = _axis_setup(u1, u2 - u1)
    j, sj, tj, dj = _axis_setup(v1, v2 - v1)
    steps = abs(int(math.floor(u2)) - i) + abs(int(math.floor(v2)) - j) + 1
    t = 0.0
    acc = 0.0
    for _ in range(steps + 1):
        t_next = min(ti, tj, 1.0)
        acc += ptr[HEADER + min(max(i, 0), nx - 1) * ny + min(max(j, 0), ny - 1)] * (t_next - t)
        if t_next >= 1.0:
            break
        t = t_next
        if ti <= tj:
            i += si
            ti += di
        else:
            j += sj
            tj += dj
    return math.sqrt(dx * dx + dy * dy) * (1.0 + ptr[H_WEIGHT] * acc)


@njit(cache=True, inline="always")
def _free_2d(ptr, x1: float, y1: float, x2: float, y2: float) -> bool:  # type: ignore[no-untyped-def]
    inv = ptr[H_INV_RES]
    nx = int(ptr[H_SHAPE])
    ny = int(ptr[H_SHAPE + 1])
    n = int(ptr[H_NCELLS])
    u1 = (x1 - ptr[H_ORIGIN]) * inv
    v1 = (y1 - ptr[H_ORIGIN + 1]) * inv
    u2 = (x2 - ptr[H_ORIGIN]) * inv
    v2 = (y2 - ptr[H_ORIGIN + 1]) * inv
    if not (0.0 <= u1 < nx and 0.0 <= v1 < ny and 0.0 <= u2 < nx and 0.0 <= v2 < ny):
        return False
    i, si, ti, di = _axis_setup(u1, u2 - u1)
    j, sj, tj, dj = _axis_setup(v1, v2 - v1)
    steps = abs(int(math.floor(u2)) - i) + abs(int(math.floor(v2)) - j) + 1
    eps_t = _eps_t(math.sqrt((u2 - u1) ** 2 + (v2 - v1) ** 2))
    t = 0.0
    for _ in range(steps + 1):
        t_next = min(ti, tj, 1.0)
        if t_next - t > eps_t and ptr[HEADER + n + min(max(i, 0), nx - 1) * ny + min(max(j, 0), ny - 1)] == 0.0:
            return False
        if t_next >= 1.0:
            return True
        t = t_next
        if ti <= tj:
            i += si
            ti += di
        else:
            j += sj
            tj += dj
    return True


@njit("boolean(intp, float64, float64, float64, float64)", cache=True)
def segment_free_2d(address: int, x1: float, y1: float, x2: float, y2: float) -> bool:
    """True when every cell a straight segment crosses is valid (packed 2-D grid)."""
    return _free_2d(_f64_ptr(address), x1, y1, x2, y2)


@njit("float64(intp, float64, float64, float64, float64, float64, float64)", cache=True)
def segment_cost_3d(address: int, x1: float, y1: float, z1: float, x2: float, y2: float, z2: float) -> float:
    """Cost ``length * (1 + w * mean risk)`` of a straight segment in a packed 3-D grid."""
    ptr = _f64_ptr(address)
    buf = carray(ptr, (HEADER + 2 * int(ptr[H_NCELLS]),))
    acc, _, _ = _walk(buf, x1, y1, z1, x2, y2, z2, False)
    dx = x2 - x1
    dy = y2 - y1
    dz = z2 - z1
    return math.sqrt(dx * dx + dy * dy + dz * dz) * (1.0 + buf[H_WEIGHT] * acc)


@njit("boolean(intp, float64, float64, float64, float64, float64, float64)", cache=True)
def segment_free_3d(address: int, x1: float, y1: float, z1: float, x2: float, y2: float, z2: float) -> bool:
    """True when every cell a straight segment crosses is valid (packed 3-D grid)."""
    ptr = _f64_ptr(address)
    buf = carray(ptr, (HEADER + 2 * int(ptr[H_NCELLS]),))
    return _walk(buf, x1, y1, z1, x2, y2, z2, True)[2]


# ---------------------------------------------------------------- whole paths


@njit(cache=True)
def evaluate_polyline(buf: np.ndarray, points: np.ndarray) -> tuple[float, float, float, int]:
    """Length, risk integral (metres x risk), peak risk and first invalid segment of a polyline.

    ``points`` is (K, 3) (z ignored in a grid one cell deep). The index of the first
    segment that leaves the grid or crosses an invalid cell is returned, -1 when none
    does; a single point is checked as a zero-length segment.
    """
    length = 0.0
    integral = 0.0
    peak = 0.0
    bad = -1
    count = points.shape[0]
    for s in range(max(count - 1, 1)):
        a = points[s]
        b = points[min(s + 1, count - 1)]
        acc, top, ok = _walk(buf, a[0], a[1], a[2], b[0], b[1], b[2], False)
        seg = math.sqrt((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2 + (b[2] - a[2]) ** 2)
        length += seg
        integral += acc * seg
        if top > peak:
            peak = top
        if not ok and bad < 0:
            bad = s
    return length, integral, peak, bad


@njit(cache=True)
def shortcut(buf: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Greedy string pulling that never raises the cost or the peak risk; returns the kept indices.

    From each kept point, the farthest later point reachable by a valid straight segment
    whose cost is not above that of the sub-path it replaces, and whose largest risk is not
    above that sub-path's, becomes the next kept point. The peak rule keeps a short cut from
    trading clearance for length: a cost linear in risk would let a path that went round a
    contested cell (risk 0.5) cut across it to save a few per cent of its length, closer
    to danger than the optimum it started from. Deterministic, and exact for the cost and
    peak of :func:`evaluate_polyline`.
    """
    count = points.shape[0]
    w = buf[H_WEIGHT]
    prefix = np.zeros(count)
    seg_peak = np.zeros(count)
    for s in range(count - 1):
        a = points[s]
        b = points[s + 1]
        acc, top, _ = _walk(buf, a[0], a[1], a[2], b[0], b[1], b[2], False)
        seg = math.sqrt((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2 + (b[2] - a[2]) ** 2)
        prefix[s + 1] = prefix[s] + seg * (1.0 + w * acc)
        seg_peak[s] = top
    keep = np.empty(count, dtype=np.int64)
    sub_peak = np.empty(count)  # sub_peak[j]: largest risk on the sub-path from point i to point j
    kept = 0
    i = 0
    keep[kept] = 0
    kept += 1
    while i < count - 1:
        top = 0.0
        for j in range(i + 1, count):
            top = max(top, seg_peak[j - 1])
            sub_peak[j] = top
        nxt = i + 1
        a = points[i]
        for j in range(count - 1, i + 1, -1):
            b = points[j]
            acc, peak, ok = _walk(buf, a[0], a[1], a[2], b[0], b[1], b[2], True)
            if not ok or peak > sub_peak[j]:
                continue
            seg = math.sqrt((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2 + (b[2] - a[2]) ** 2)
            if seg * (1.0 + w * acc) <= prefix[j] - prefix[i] + 1e-12 * (1.0 + prefix[j]):
                nxt = j
                break
        keep[kept] = nxt
        kept += 1
        i = nxt
    return keep[:kept]


# ---------------------------------------------------------------- grid search


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


# ---------------------------------------------------------------- Dubins curves
# The shortest of the six Dubins words (Dubins 1957; closed forms of Shkel & Lumelsky 2001, as
# OMPL's DubinsStateSpace computes them), so a motion's cost and validity are computed along the
# very curve OMPL interpolates. Lengths are in units of the turning radius.

DUBINS_EPS = 1e-6
DUBINS_ZERO = -1e-7
_TWO_PI = 2.0 * math.pi
# segment turn per word: +1 left, 0 straight, -1 right (LSL, RSR, RSL, LSR, RLR, LRL: OMPL's order)
DUBINS_TURNS = np.array([[1, 0, 1], [-1, 0, -1], [-1, 0, 1], [1, 0, -1], [-1, 1, -1], [1, -1, 1]], dtype=np.int64)


@njit(cache=True, inline="always")
def _mod2pi(x: float) -> float:
    if -(10.0 * DUBINS_EPS) < x < 0.0:
        return 0.0
    xm = x - _TWO_PI * math.floor(x / _TWO_PI)
    if _TWO_PI - xm < 0.5 * DUBINS_EPS:
        xm = 0.0
    return xm


@njit(cache=True)
def dubins_word(d: float, alpha: float, beta: float) -> tuple[int, float, float, float]:
    """Shortest Dubins word from (0, 0, alpha) to (d, 0, beta): (word, t, p, q), unit radius."""
    if d < DUBINS_EPS and abs(alpha - beta) < DUBINS_EPS:
        return 0, 0.0, d, 0.0
    ca = math.cos(alpha)
    sa = math.sin(alpha)
    cb = math.cos(beta)
    sb = math.sin(beta)
    best = -1
    bt = bp = bq = 0.0
    blen = math.inf
    # LSL
    tmp = 2.0 + d * d - 2.0 * (ca * cb + sa * sb - d * (sa - sb))
    if tmp >= DUBINS_ZERO:
        theta = math.atan2(cb - ca, d + sa - sb)
        t = _mod2pi(-alpha + theta)
        p = math.sqrt(max(tmp, 0.0))
        q = _mod2pi(beta - theta)
        if t + p + q < blen:
            best, bt, bp, bq, blen = 0, t, p, q, t + p + q
    # RSR
    tmp = 2.0 + d * d - 2.0 * (ca * cb + sa * sb - d * (sb - sa))
    if tmp >= DUBINS_ZERO:
        theta = math.atan2(ca - cb, d - sa + sb)
        t = _mod2pi(alpha - theta)
        p = math.sqrt(max(tmp, 0.0))
        q = _mod2pi(-beta + theta)
        if t + p + q < blen:
            best, bt, bp, bq, blen = 1, t, p, q, t + p + q
    # RSL
    tmp = d * d - 2.0 + 2.0 * (ca * cb + sa * sb - d * (sa + sb))
    if tmp >= DUBINS_ZERO:
        p = math.sqrt(max(tmp, 0.0))
        theta = math.atan2(ca + cb, d - sa - sb) - math.atan2(2.0, p)
        t = _mod2pi(alpha - theta)
        q = _mod2pi(beta - theta)
        if t + p + q < blen:
            best, bt, bp, bq, blen = 2, t, p, q, t + p + q
    # LSR
    tmp = -2.0 + d * d + 2.0 * (ca * cb + sa * sb + d * (sa + sb))
    if tmp >= DUBINS_ZERO:
        p = math.sqrt(max(tmp, 0.0))
        theta = math.atan2(-ca - cb, d + sa + sb) - math.atan2(-2.0, p)
        t = _mod2pi(-alpha + theta)
        q = _mod2pi(-beta + theta)
        if t + p + q < blen:
            best, bt, bp, bq, blen = 3, t, p, q, t + p + q
    # RLR
    tmp = 0.125 * (6.0 - d * d + 2.0 * (ca * cb + sa * sb + d * (sa - sb)))
    if abs(tmp) < 1.0:
        p = _TWO_PI - math.acos(tmp)
        theta = math.atan2(ca - cb, d - sa + sb)
        t = _mod2pi(alpha - theta + 0.5 * p)
        q = _mod2pi(alpha - beta - t + p)
        if t + p + q < blen:
            best, bt, bp, bq, blen = 4, t, p, q, t + p + q
    # LRL
    tmp = 0.125 * (6.0 - d * d + 2.0 * (ca * cb + sa * sb - d * (sa - sb)))
    if abs(tmp) < 1.0:
        p = _TWO_PI - math.acos(tmp)
        theta = math.atan2(-ca + cb, d + sa - sb)
        t = _mod2pi(-alpha + theta + 0.5 * p)
        q = _mod2pi(beta - alpha - t + p)
        if t + p + q < blen:
            best, bt, bp, bq, blen = 5, t, p, q, t + p + q
    return best, bt, bp, bq


@njit(cache=True, inline="always")
def _dubins_between(
    x1: float, y1: float, th1: float, x2: float, y2: float, th2: float, rho: float
) -> tuple[int, float, float, float]:
    dx = x2 - x1
    dy = y2 - y1
    d = math.sqrt(dx * dx + dy * dy) / rho
    th = math.atan2(dy, dx)
    return dubins_word(d, _mod2pi(th1 - th), _mod2pi(th2 - th))


@njit(cache=True)
def dubins_point(
    x1: float, y1: float, th1: float, rho: float, word: int, t: float, p: float, q: float, s: float
) -> tuple[float, float, float]:
    """Pose at arc length ``s`` (units of rho) along a Dubins word from (x1, y1, th1)."""
    x = 0.0
    y = 0.0
    phi = th1
    lengths = (t, p, q)
    for k in range(3):
        if s <= 0.0:
            break
        v = min(s, lengths[k])
        s -= v
        turn = DUBINS_TURNS[word, k]
        if turn == 1:
            x += math.sin(phi + v) - math.sin(phi)
            y += -math.cos(phi + v) + math.cos(phi)
            phi += v
        elif turn == -1:
            x += -math.sin(phi - v) + math.sin(phi)
            y += math.cos(phi - v) - math.cos(phi)
            phi -= v
        else:
            x += v * math.cos(phi)
            y += v * math.sin(phi)
    return x * rho + x1, y * rho + y1, phi


@njit("float64(intp, float64, float64, float64, float64, float64, float64)", cache=True)
def dubins_length(address: int, x1: float, y1: float, th1: float, x2: float, y2: float, th2: float) -> float:
    """Length (metres) of the Dubins curve between two poses (the packed turning radius)."""
    rho = _f64_ptr(address)[H_RHO]
    _, t, p, q = _dubins_between(x1, y1, th1, x2, y2, th2, rho)
    return (t + p + q) * rho


@njit("float64(intp, float64, float64, float64, float64, float64, float64)", cache=True)
def dubins_cost(address: int, x1: float, y1: float, th1: float, x2: float, y2: float, th2: float) -> float:
    """``length + w * risk integral`` along the Dubins curve (midpoint rule, one sample per cell)."""
    ptr = _f64_ptr(address)
    rho = ptr[H_RHO]
    inv = ptr[H_INV_RES]
    ox = ptr[H_ORIGIN]
    oy = ptr[H_ORIGIN + 1]
    nx = int(ptr[H_SHAPE])
    ny = int(ptr[H_SHAPE + 1])
    word, t, p, q = _dubins_between(x1, y1, th1, x2, y2, th2, rho)
    total = t + p + q
    length = total * rho
    n = int(length * inv) + 1
    acc = 0.0
    for k in range(n):
        x, y, _ = dubins_point(x1, y1, th1, rho, word, t, p, q, total * (k + 0.5) / n)
        i = min(max(int(math.floor((x - ox) * inv)), 0), nx - 1)
        j = min(max(int(math.floor((y - oy) * inv)), 0), ny - 1)
        acc += ptr[HEADER + i * ny + j]
    return length * (1.0 + ptr[H_WEIGHT] * acc / n)


@njit("boolean(intp, float64, float64, float64, float64, float64, float64)", cache=True)
def dubins_free(address: int, x1: float, y1: float, th1: float, x2: float, y2: float, th2: float) -> bool:
    """True when the Dubins curve crosses only valid cells.

    The curve is cut into chords of at most a quarter cell, at the very points ``plan``
    verifies (OMPL's interpolation at k / n, n = ceil(length / (res / 4))), and every cell
    each chord crosses is checked. A chord strays from its arc by at most
    (res / 4)^2 / (8 rho), under 0.1 % of a cell for rho >= res.
    """
    ptr = _f64_ptr(address)
    rho = ptr[H_RHO]
    word, t, p, q = _dubins_between(x1, y1, th1, x2, y2, th2, rho)
    total = t + p + q
    n = max(1, int(math.ceil(4.0 * total * rho * ptr[H_INV_RES])))
    px = x1
    py = y1
    for k in range(1, n + 1):
        x, y, _ = dubins_point(x1, y1, th1, rho, word, t, p, q, total * k / n)
        if not _free_2d(ptr, px, py, x, y):
            return False
        px = x
        py = y
    return True


# ---------------------------------------------------------------- box maxima (the dilation by the robot)
# What ndimage.maximum_filter did before (issue 15: an image without its library). A maximum rounds
# nothing, so any order of comparisons gives the same result; what matters is speed. Every loop
# indexes its arrays by the loop variable alone, views made outside it: an offset index (x[t + k]) keeps
# LLVM from vectorising the loop (3-10 times slower).

@njit(cache=True)
def _fill(dst, value):  # type: ignore[no-untyped-def]
    for c in range(dst.size):
        dst[c] = value


@njit(cache=True)
def _copy(dst, x):  # type: ignore[no-untyped-def]
    for c in range(dst.size):
        dst[c] = x[c]


@njit(cache=True)
def _max2(dst, x, y):  # type: ignore[no-untyped-def]
    for c in range(dst.size):
        a = x[c]
        b = y[c]
        dst[c] = a if a > b else b


@njit(cache=True)
def _max_in(dst, y):  # type: ignore[no-untyped-def]
    """``dst`` keeps the larger of itself and ``y`` (not ``_max2(dst, dst, y)``: LLVM would not
    vectorise a loop whose destination is one of its sources as that function sees it)."""
    for c in range(dst.size):
        a = dst[c]
        b = y[c]
        dst[c] = a if a > b else b


@njit(cache=True)
def _max3(dst, x, y):  # type: ignore[no-untyped-def]
    """``dst`` keeps the largest of itself, ``x`` and ``y``."""
    for c in range(dst.size):
        a = x[c]
        b = y[c]
        a = a if a > b else b
        b = dst[c]
        dst[c] = a if a > b else b


@njit(cache=True)
def _line_max(dst, line, half, cval, a, b, accumulate):  # type: ignore[no-untyped-def]
    """Maximum over ``2 half + 1`` cells of ``line``, ``cval`` beyond its ends, into ``dst``.

    In the padded buffer ``a`` (``b`` the same size): maxima over 1, 2, 4, ... cells, each a
    vectorised pass, then the window as two overlapping powers of two.
    """
    m = line.size
    if half == 0:
        if accumulate:
            _max_in(dst, line)
        else:
            _copy(dst, line)
        return
    width = 2 * half + 1
    span = m + 2 * half
    _fill(a[:half], cval)
    _fill(a[half + m : span], cval)
    _copy(a[half : half + m], line)
    top = 1  # the largest power of two in the window
    while 2 * top <= width:
        top *= 2
    cur, nxt = a, b
    step = 1
    while step < top:
        k = span - 2 * step + 1
        _max2(nxt[:k], cur[:k], cur[step : step + k])
        cur, nxt = nxt, cur
        step *= 2
    lag = width - top
    if accumulate:
        _max3(dst, cur[:m], cur[lag : lag + m])
    else:
        _max2(dst, cur[:m], cur[lag : lag + m])


@njit(cache=True)
def _suffix_max(rows, width, m):  # type: ignore[no-untyped-def]
    for k in range(width - 2, -1, -1):
        _max_in(rows[k * m : (k + 1) * m], rows[(k + 1) * m : (k + 2) * m])


@njit(cache=True, nogil=True)  # a big map's dilation takes a while: other threads run meanwhile
def box_max_2d(src, outer, n, m, half_n, half_m, cval, out, accumulate):  # type: ignore[no-untyped-def]
    """Maximum over boxes of ``2 half_n + 1`` rows by ``2 half_m + 1`` columns, ``cval`` beyond the ends.

    ``src`` and ``out`` are C-ordered (outer, n, m) arrays, flattened: ``out[o, i, j]`` becomes the
    maximum of ``src[o, i - half_n : i + half_n + 1, j - half_m : j + half_m + 1]``, or with
    ``accumulate`` the larger of that and its own value. ``out`` may be ``src`` unless ``accumulate``.
    Compiled once per dtype (float32, uint8) if ``src`` always comes read-only (``field._box_max``).

    Rows filtered along themselves (``_line_max``) are combined along ``n`` by van Herk /
    Gil-Werman over blocks of ``width`` rows: the window at row i is the suffix of its block from
    i and the prefix of the next block, 3 comparisons a cell whatever the width. Whole rows at a
    time, each source row read once and before its own output row is written (hence in place).
    """
    a = np.empty(m + 2 * half_m, src.dtype)
    b = np.empty(m + 2 * half_m, src.dtype)
    size = n * m
    if half_n == 0:
        for o in range(outer):
            for i in range(n):
                s = o * size + i * m
                _line_max(out[s : s + m], src[s : s + m], half_m, cval, a, b, accumulate)
        return
    width = 2 * half_n + 1
    rows = np.empty(width * m, src.dtype)  # a block's filtered rows, then their suffix maxima in place
    prefix = np.empty(m, src.dtype)
    for o in range(outer):
        plane = src[o * size : (o + 1) * size]
        oplane = out[o * size : (o + 1) * size]
        for k in range(width):  # padded rows 0 .. width - 1 are source rows -half_n ..
            r = k - half_n
            slot = rows[k * m : (k + 1) * m]
            if 0 <= r < n:
                _line_max(slot, plane[r * m : (r + 1) * m], half_m, cval, a, b, False)
            else:
                _fill(slot, cval)
        _suffix_max(rows, width, m)
        for blk in range(0, n, width):
            for k in range(width):
                i = blk + k
                if i >= n:
                    break
                slot = rows[k * m : (k + 1) * m]
                dst = oplane[i * m : (i + 1) * m]
                if k == 0:  # the window is the block
                    if accumulate:
                        _max_in(dst, slot)
                    else:
                        _copy(dst, slot)
                elif accumulate:
                    _max3(dst, slot, prefix)
                else:
                    _max2(dst, slot, prefix)
                # the slot is free: the next block's row k goes there, and joins its prefix
                r = blk + width + k - half_n
                if 0 <= r < n:
                    _line_max(slot, plane[r * m : (r + 1) * m], half_m, cval, a, b, False)
                else:
                    _fill(slot, cval)
                if k == 0:
                    _copy(prefix, slot)
                else:
                    _max_in(prefix, slot)
            if blk + width < n:
                _suffix_max(rows, width, m)
