"""Compiled Dubins curves over a packed risk grid: length, cost and validity of a motion.

The shortest of the six Dubins words (Dubins 1957; closed forms of Shkel & Lumelsky 2001, as
OMPL's DubinsStateSpace computes them), so a motion's cost and validity are computed along the
very curve OMPL interpolates. Lengths are in units of the turning radius.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from planning._segment_kernels import H_INV_RES, H_ORIGIN, H_RHO, H_SHAPE, H_WEIGHT, HEADER, f64_ptr, free_2d_ptr

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
    rho = f64_ptr(address)[H_RHO]
    _, t, p, q = _dubins_between(x1, y1, th1, x2, y2, th2, rho)
    return (t + p + q) * rho


@njit("float64(intp, float64, float64, float64, float64, float64, float64)", cache=True)
def dubins_cost(address: int, x1: float, y1: float, th1: float, x2: float, y2: float, th2: float) -> float:
    """``length + w * risk integral`` along the Dubins curve (midpoint rule, one sample per cell)."""
    ptr = f64_ptr(address)
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
    ptr = f64_ptr(address)
    rho = ptr[H_RHO]
    word, t, p, q = _dubins_between(x1, y1, th1, x2, y2, th2, rho)
    total = t + p + q
    n = max(1, int(math.ceil(4.0 * total * rho * ptr[H_INV_RES])))
    px = x1
    py = y1
    for k in range(1, n + 1):
        x, y, _ = dubins_point(x1, y1, th1, rho, word, t, p, q, total * k / n)
        if not free_2d_ptr(ptr, px, py, x, y):
            return False
        px = x
        py = y
    return True
