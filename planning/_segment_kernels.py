"""Compiled walks of straight segments through a packed risk grid: cost, validity, whole paths.

Everything the planners call per edge lives here (and in ``_dubins_kernels``), compiled by
numba, because the objective and the motion validator are called from C++ for every edge and
their cost per call is the planner's speed (``notes/ompl-2.0-python.md``).

The grid is packed once per query into one contiguous float64 buffer (see :func:`pack`; the
other kernel modules read its header too), so a hot kernel takes one integer (the buffer's
address) and the segment's coordinates: numba unboxes scalars much faster than arrays, which
is most of the price of a call from Python.

Segments are walked cell by cell (Amanatides & Woo, "A fast voxel traversal
algorithm for ray tracing", 1987) in grid units ``u = (p - origin) / resolution``:
the walk visits every cell in which the segment has positive length, so the risk
integral is exact for the piecewise-constant field and the validity check misses no
cell however thin. A 2-D grid is packed as a 3-D grid one cell deep.
"""

from __future__ import annotations

import math
from typing import Any

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


def pointer_to(pointee: types.Type) -> Any:
    """An intrinsic reinterpreting an integer address as a pointer to ``pointee`` (its owner keeps the memory alive)."""
    pointer = types.CPointer(pointee)

    def cast(typingctx, address):  # type: ignore[no-untyped-def]
        def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
            return builder.inttoptr(args[0], context.get_value_type(pointer))

        return pointer(types.intp), codegen

    cast.__name__ = cast.__qualname__ = f"{pointee}_ptr"  # one name per intrinsic
    return intrinsic(cast)


#: ``double*`` at an integer address: the packed buffer as the hot kernels read it.
f64_ptr = pointer_to(types.float64)


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
    ptr = f64_ptr(address)
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
def free_2d_ptr(ptr, x1: float, y1: float, x2: float, y2: float) -> bool:  # type: ignore[no-untyped-def]
    """:func:`segment_free_2d` through a pointer already made (``dubins_free`` checks its chords with it)."""
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
    return free_2d_ptr(f64_ptr(address), x1, y1, x2, y2)


@njit("float64(intp, float64, float64, float64, float64, float64, float64)", cache=True)
def segment_cost_3d(address: int, x1: float, y1: float, z1: float, x2: float, y2: float, z2: float) -> float:
    """Cost ``length * (1 + w * mean risk)`` of a straight segment in a packed 3-D grid."""
    ptr = f64_ptr(address)
    buf = carray(ptr, (HEADER + 2 * int(ptr[H_NCELLS]),))
    acc, _, _ = _walk(buf, x1, y1, z1, x2, y2, z2, False)
    dx = x2 - x1
    dy = y2 - y1
    dz = z2 - z1
    return math.sqrt(dx * dx + dy * dy + dz * dz) * (1.0 + buf[H_WEIGHT] * acc)


@njit("boolean(intp, float64, float64, float64, float64, float64, float64)", cache=True)
def segment_free_3d(address: int, x1: float, y1: float, z1: float, x2: float, y2: float, z2: float) -> bool:
    """True when every cell a straight segment crosses is valid (packed 3-D grid)."""
    ptr = f64_ptr(address)
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
    return evaluate_walk(buf, points, points)


@njit(cache=True, nogil=True)  # a path check runs in the service's read threads: other requests run meanwhile
def evaluate_walk(buf: np.ndarray, walk: np.ndarray, points: np.ndarray) -> tuple[float, float, float, int]:
    """:func:`evaluate_polyline` of ``points``, its cells walked along ``walk``: the same polyline in the buffer's frame.

    ``walk`` places each point in the grid the buffer holds (header origin and resolution), ``points``
    gives the lengths in metres. ``planning.path_check`` packs a window of a map with origin 0 and
    resolution 1, and walks each point's cell coordinates in the whole map less the window's offset:
    the walk then meets the same cells at the same parameters as on the whole map, bit for bit.
    """
    length = 0.0
    integral = 0.0
    peak = 0.0
    bad = -1
    count = points.shape[0]
    for s in range(max(count - 1, 1)):
        a = walk[s]
        b = walk[min(s + 1, count - 1)]
        acc, top, ok = _walk(buf, a[0], a[1], a[2], b[0], b[1], b[2], False)
        p = points[s]
        q = points[min(s + 1, count - 1)]
        seg = math.sqrt((q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2 + (q[2] - p[2]) ** 2)
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
