"""Piecewise-linear membership functions and a check that a set of them covers an axis.

Every membership function here is a small frozen dataclass that is piecewise
linear with constant extension beyond its outermost breakpoints, so it
evaluates with one ``np.interp`` over any array shape, and the set where it is
strictly positive is one open interval (``support``). That makes coverage of an
axis an exact interval sweep rather than a sampled guess.

>>> import numpy as np
>>> Triangle(-1.0, 0.0, 1.5)(np.array([-1.0, -0.5, 0.0, 0.75]))
array([0. , 0.5, 1. , 0.5])
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "LeftShoulder",
    "MembershipFunction",
    "RightShoulder",
    "Trapezoid",
    "Triangle",
    "check_coverage",
    "coverage_gaps",
    "ladder",
]


def _finite(cls_name: str, **values: float) -> None:
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
            raise ValueError(f"{cls_name}.{name} must be a finite number, got {value!r}")


def _increasing(cls_name: str, names: Sequence[str], values: Sequence[float], strict: Sequence[bool]) -> None:
    for k in range(len(values) - 1):
        a, b = values[k], values[k + 1]
        if (strict[k] and not a < b) or (not strict[k] and not a <= b):
            rel = "<" if strict[k] else "<="
            raise ValueError(
                f"{cls_name} needs {names[k]} {rel} {names[k + 1]}, got {names[k]}={a!r}, {names[k + 1]}={b!r}"
            )


@dataclass(frozen=True)
class MembershipFunction:
    """Base of the piecewise-linear membership functions (not used directly).

    Subclasses define ``breakpoints`` (strictly increasing ``xs`` and their
    values ``ys`` in [0, 1]); the function is linear between them and constant
    beyond them.
    """

    @property
    def breakpoints(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """``(xs, ys)``: strictly increasing abscissae and the membership at each."""
        raise NotImplementedError

    def __call__(self, x: np.ndarray | float) -> np.ndarray:
        """Membership of every element of ``x`` (any shape), float64 in [0, 1]; NaN stays NaN."""
        xs, ys = self.breakpoints
        return np.interp(np.asarray(x, dtype=np.float64), xs, ys)

    @property
    def support(self) -> tuple[float, float]:
        """The open interval ``(lo, hi)`` where the membership is > 0 (ends may be infinite)."""
        raise NotImplementedError


@dataclass(frozen=True)
class LeftShoulder(MembershipFunction):
    """1 up to ``top_end``, falling linearly to 0 at ``zero_at``, 0 beyond.

    Parameters
    ----------
    top_end, zero_at : float
        Finite, ``top_end < zero_at``.
    """

    top_end: float
    zero_at: float

    def __post_init__(self) -> None:
        _finite("LeftShoulder", top_end=self.top_end, zero_at=self.zero_at)
        _increasing("LeftShoulder", ("top_end", "zero_at"), (self.top_end, self.zero_at), (True,))

    @property
    def breakpoints(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (float(self.top_end), float(self.zero_at)), (1.0, 0.0)

    @property
    def support(self) -> tuple[float, float]:
        return -math.inf, float(self.zero_at)


@dataclass(frozen=True)
class RightShoulder(MembershipFunction):
    """0 up to ``zero_at``, rising linearly to 1 at ``top_start``, 1 beyond.

    Parameters
    ----------
    zero_at, top_start : float
        Finite, ``zero_at < top_start``.
    """

    zero_at: float
    top_start: float

    def __post_init__(self) -> None:
        _finite("RightShoulder", zero_at=self.zero_at, top_start=self.top_start)
        _increasing("RightShoulder", ("zero_at", "top_start"), (self.zero_at, self.top_start), (True,))

    @property
    def breakpoints(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (float(self.zero_at), float(self.top_start)), (0.0, 1.0)

    @property
    def support(self) -> tuple[float, float]:
        return float(self.zero_at), math.inf


@dataclass(frozen=True)
class Triangle(MembershipFunction):
    """0 at ``left``, 1 at ``peak``, 0 at ``right`` (and 0 outside).

    Parameters
    ----------
    left, peak, right : float
        Finite, ``left < peak < right``.
    """

    left: float
    peak: float
    right: float

    def __post_init__(self) -> None:
        _finite("Triangle", left=self.left, peak=self.peak, right=self.right)
        _increasing("Triangle", ("left", "peak", "right"), (self.left, self.peak, self.right), (True, True))

    @property
    def breakpoints(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (float(self.left), float(self.peak), float(self.right)), (0.0, 1.0, 0.0)

    @property
    def support(self) -> tuple[float, float]:
        return float(self.left), float(self.right)


@dataclass(frozen=True)
class Trapezoid(MembershipFunction):
    """0 at ``a``, 1 from ``b`` to ``c``, 0 at ``d`` (and 0 outside).

    Parameters
    ----------
    a, b, c, d : float
        Finite, ``a < b <= c < d`` (``b == c`` is a triangle).
    """

    a: float
    b: float
    c: float
    d: float

    def __post_init__(self) -> None:
        _finite("Trapezoid", a=self.a, b=self.b, c=self.c, d=self.d)
        _increasing("Trapezoid", ("a", "b", "c", "d"), (self.a, self.b, self.c, self.d), (True, False, True))

    @property
    def breakpoints(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        if self.b == self.c:
            return (float(self.a), float(self.b), float(self.d)), (0.0, 1.0, 0.0)
        return (float(self.a), float(self.b), float(self.c), float(self.d)), (0.0, 1.0, 1.0, 0.0)

    @property
    def support(self) -> tuple[float, float]:
        return float(self.a), float(self.d)


def ladder(peaks: Sequence[float]) -> tuple[MembershipFunction, ...]:
    """A strong fuzzy partition: shoulders at both ends, triangles reaching the neighbouring peaks.

    ``peaks[0]`` is where the left shoulder's plateau ends and ``peaks[-1]``
    where the right shoulder's begins; every function falls to 0 at its
    neighbours' peaks, so at every x at most two are positive and they sum to 1.

    Parameters
    ----------
    peaks : sequence of float
        At least 2, finite, strictly increasing.

    Returns
    -------
    tuple of MembershipFunction
        ``len(peaks)`` functions, left to right.

    Examples
    --------
    >>> left, middle, right = ladder([0.0, 0.5, 1.0])
    >>> middle
    Triangle(left=0.0, peak=0.5, right=1.0)
    >>> float(left(0.25) + middle(0.25) + right(0.25))
    1.0
    """
    p = [float(v) for v in peaks]
    if len(p) < 2:
        raise ValueError(f"peaks needs at least 2 values, got {len(p)}")
    _finite("ladder", **{f"peaks[{k}]": v for k, v in enumerate(p)})
    _increasing("ladder", [f"peaks[{k}]" for k in range(len(p))], p, [True] * (len(p) - 1))
    middle = tuple(Triangle(p[k - 1], p[k], p[k + 1]) for k in range(1, len(p) - 1))
    return (LeftShoulder(p[0], p[1]), *middle, RightShoulder(p[-2], p[-1]))


def _fmt(x: float) -> str:
    return "inf" if x == math.inf else "-inf" if x == -math.inf else f"{x:g}"


def coverage_gaps(
    mfs: Iterable[MembershipFunction], lo: float = -math.inf, hi: float = math.inf
) -> list[tuple[float, float]]:
    """Parts of the closed axis ``[lo, hi]`` where every membership function is 0.

    Parameters
    ----------
    mfs : iterable of MembershipFunction
    lo, hi : float
        Ends of the axis. An infinite end is covered when some function stays
        positive all the way out (a shoulder).

    Returns
    -------
    list of (float, float)
        Closed gaps ``[a, b]`` in increasing order, ``a == b`` for a single
        uncovered point (two supports that merely touch). Empty when covered.

    Examples
    --------
    >>> coverage_gaps([LeftShoulder(-1.0, 0.0), RightShoulder(0.0, 1.0)])
    [(0.0, 0.0)]
    """
    if not lo <= hi:
        raise ValueError(f"axis needs lo <= hi, got lo={lo!r}, hi={hi!r}")
    # Supports are open intervals: x is covered iff lo_k < x < hi_k for some k. Sweep them by
    # their left ends; `cur` is the leftmost point of the axis not yet known to be covered.
    gaps: list[tuple[float, float]] = []
    cur = lo
    for s_lo, s_hi in sorted(mf.support for mf in mfs):
        if cur > hi or cur == math.inf:
            break
        if s_hi <= cur:
            continue
        # -inf is not a point: an interval open to -inf covers everything below its right end.
        if not (s_lo < cur or s_lo == cur == -math.inf):
            gaps.append((cur, min(s_lo, hi)))  # later supports all start at or after s_lo
        cur = s_hi
    if cur < hi or (cur == hi and not math.isinf(hi)):
        gaps.append((cur, hi))
    return gaps


def check_coverage(mfs: Iterable[MembershipFunction], lo: float, hi: float, what: str) -> None:
    """Raise ``ValueError`` naming ``what`` and the exact gaps when ``mfs`` do not cover ``[lo, hi]``."""
    gaps = coverage_gaps(mfs, lo, hi)
    if gaps:
        where = ", ".join(f"x = {_fmt(a)}" if a == b else f"[{_fmt(a)}, {_fmt(b)}]" for a, b in gaps)
        raise ValueError(
            f"{what} do not cover the axis [{_fmt(lo)}, {_fmt(hi)}]: every membership is 0 at {where}"
        )
