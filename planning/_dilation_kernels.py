"""Compiled box maxima: the dilation of a risk grid by the robot's footprint (``field.py``).

What ``ndimage.maximum_filter`` did before SciPy left the service's dependencies (a smaller
image). A maximum rounds nothing, so any order of comparisons gives the same result; what
matters is speed. Every loop indexes its arrays by the loop variable alone, views made outside
it: an offset index (``x[t + k]``) keeps LLVM from vectorising the loop (3-10 times slower).
"""

from __future__ import annotations

import numpy as np
from numba import njit


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
