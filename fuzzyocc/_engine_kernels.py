"""The fuzzy engine's compiled loops: fuzzify distances, fuse states by the rule table, defuzzify by table.

:class:`fuzzyocc.engine.FuzzyEngine` checks the arguments and holds the tables these loops read;
``fuzzyocc.grid.BlockGrid`` inlines :func:`evidence_class`, :func:`fuzzify_into` and
:func:`fuse_row` in its own loop, so a map's cells are fuzzified and fused with the very
arithmetic of :meth:`~fuzzyocc.engine.FuzzyEngine.fuzzify` and :meth:`~fuzzyocc.engine.FuzzyEngine.fuse`.
Every kernel is ``nogil``: maps fuse in a service's thread pool, and these loops touch no Python object.
"""

from __future__ import annotations

import numba
import numpy as np

#: Risk of a state with no activation at all (no output set): unknown.
UNKNOWN_RISK = 0.5

#: Classes of a distance that :func:`evidence_class` gives: every input function constant.
BELOW, ABOVE, FLAT = 0, 1, 2
#: The class of a distance where some input function slopes: fuzzified by :func:`fuzzify_into`.
SLOPED = 3


@numba.njit(cache=True, nogil=True, inline="always")
def evidence_class(v: float, bounds: np.ndarray) -> int:  # pragma: no cover - compiled
    """Which row a distance fuzzifies to: ``rows[BELOW]`` below every function's first breakpoint,
    ``rows[ABOVE]`` past every last one, ``rows[FLAT]`` on the widest interval where every
    function is flat, else ``SLOPED`` (NaN too: callers reject it first).

    Most cells of a beam lie far in front of its surface, where the row is a constant.
    """
    if v < bounds[0]:
        return BELOW
    if v > bounds[1]:
        return ABOVE
    if bounds[2] < v < bounds[3]:
        return FLAT
    return SLOPED


@numba.njit(cache=True, nogil=True, inline="always")
def fuzzify_into(
    v: float, xs: np.ndarray, ys: np.ndarray, counts: np.ndarray, out: np.ndarray, r: int
) -> None:  # pragma: no cover - compiled
    """``out[r]`` = the activations of every label at distance ``v`` (piecewise-linear interpolation)."""
    for k in range(xs.shape[0]):
        c = counts[k]
        if v <= xs[k, 0]:
            mu = ys[k, 0]
        elif v >= xs[k, c - 1]:
            mu = ys[k, c - 1]
        else:
            s = 1
            while xs[k, s] < v:
                s += 1
            x0 = xs[k, s - 1]
            t = (v - x0) / (xs[k, s] - x0)
            mu = ys[k, s - 1] + t * (ys[k, s] - ys[k, s - 1])
        out[r, k] = np.uint8(mu * 255.0 + 0.5)


@numba.njit(cache=True, nogil=True)
def fuzzify_distances(
    d: np.ndarray, xs: np.ndarray, ys: np.ndarray, counts: np.ndarray, rows: np.ndarray, bounds: np.ndarray,
    out: np.ndarray,
) -> int:
    """Every distance's activations into ``out``; the index of a NaN, or -1."""
    n_labels = xs.shape[0]
    for n in range(d.shape[0]):
        v = d[n]
        if v != v:
            return n
        cls = evidence_class(v, bounds)
        if cls == SLOPED:
            fuzzify_into(v, xs, ys, counts, out, n)
        else:
            for k in range(n_labels):
                out[n, k] = rows[cls, k]
    return -1



@numba.njit(cache=True, nogil=True, inline="always")
def _minmax_row(
    state: np.ndarray, c: int, evidence: np.ndarray, n: int, rule: np.ndarray, acc: np.ndarray, active: np.ndarray
) -> None:
    """``acc`` = fusion of ``state[c]`` with ``evidence[n]`` by min/max in uint8."""
    n_labels = acc.shape[0]
    # Evidence and states are sparse (one or two labels): only rules on active pairs can fire.
    n_active = 0
    for j in range(n_labels):
        acc[j] = 0
        if evidence[n, j] != 0:
            active[n_active] = j
            n_active += 1
    for i in range(n_labels):
        s = state[c, i]
        if s == 0:
            continue
        for a in range(n_active):
            j = active[a]
            v = min(s, evidence[n, j])
            k = rule[i, j]
            if v > acc[k]:
                acc[k] = v


@numba.njit(cache=True, nogil=True, inline="always")
def fuse_row(
    state: np.ndarray,
    c: int,
    evidence: np.ndarray,
    n: int,
    rule: np.ndarray,
    float_ops: tuple[bool, bool, bool] | None,
    out_row: np.ndarray,
    acc: np.ndarray,
    active: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out_row`` = :meth:`~fuzzyocc.engine.FuzzyEngine.fuse` of ``state[c]`` with ``evidence[n]`` (numba only).

    ``rule, float_ops`` come from :meth:`~fuzzyocc.engine.FuzzyEngine.row_fusion`; ``acc`` is (L,) float64
    and ``active`` (L,) int64 scratch. ``float_ops`` None is pruned at compile time: the
    min/max path is compiled alone (with both paths in one body it runs ~30% slower).
    """
    if float_ops is None:
        _minmax_row(state, c, evidence, n, rule, out_row, active)
    else:
        _float_row(state, c, evidence, n, rule, float_ops[0], float_ops[1], float_ops[2], acc, out_row)


@numba.njit(cache=True, nogil=True, inline="always")
def _float_row(
    state: np.ndarray,
    c: int,
    evidence: np.ndarray,
    n: int,
    rule: np.ndarray,
    product: bool,
    probsum: bool,
    normalize: bool,
    acc: np.ndarray,
    out_row: np.ndarray,
) -> None:
    """``out_row`` = fusion of ``state[c]`` with ``evidence[n]`` in float, rounded once to uint8."""
    n_labels = acc.shape[0]
    acc[:] = 0.0
    for i in range(n_labels):
        if state[c, i] == 0:
            continue
        s = state[c, i] / 255.0
        for j in range(n_labels):
            if evidence[n, j] == 0:
                continue
            e = evidence[n, j] / 255.0
            v = s * e if product else min(s, e)
            k = rule[i, j]
            acc[k] = acc[k] + v - acc[k] * v if probsum else max(acc[k], v)
    scale = 255.0
    if normalize:
        top = acc.max()
        if top > 0.0:
            scale = 255.0 / top
    for k in range(n_labels):
        out_row[k] = np.uint8(acc[k] * scale + 0.5)


@numba.njit(cache=True, nogil=True)
def fuse_rows(
    state: np.ndarray, evidence: np.ndarray, rule: np.ndarray, float_ops: tuple[bool, bool, bool] | None,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out[n]`` = :func:`fuse_row` of ``state[n]`` with ``evidence[n]``, for every row."""
    n_labels = state.shape[1]
    row = np.empty(n_labels, dtype=np.uint8)
    acc = np.zeros(n_labels)
    active = np.empty(n_labels, dtype=np.int64)
    for n in range(state.shape[0]):
        fuse_row(state, n, evidence, n, rule, float_ops, row, acc, active)
        for k in range(n_labels):
            out[n, k] = row[k]


@numba.njit(cache=True, nogil=True)
def pair_table(
    mu_i: np.ndarray, mu_j: np.ndarray, x: np.ndarray, product: bool, probsum: bool, out: np.ndarray
) -> None:
    """``out[a, b] = (area, moment)`` of the aggregated cuts of two output functions at levels a/255, b/255."""
    for a in range(256):
        level_a = a / 255.0
        for b in range(256):
            level_b = b / 255.0
            area = 0.0
            moment = 0.0
            for p in range(x.shape[0]):
                u = mu_i[p] * level_a if product else min(mu_i[p], level_a)
                v = mu_j[p] * level_b if product else min(mu_j[p], level_b)
                w = u + v - u * v if probsum else max(u, v)
                area += w
                moment += w * x[p]
            out[a, b, 0] = area
            out[a, b, 1] = moment


@numba.njit(cache=True, nogil=True)
def defuzzify_lut(state: np.ndarray, first: np.ndarray, second: np.ndarray, lut: np.ndarray, out: np.ndarray) -> None:
    for n in range(state.shape[0]):
        area = 0.0
        moment = 0.0
        for f in range(first.shape[0]):
            idx = np.int64(state[n, first[f]]) * 256
            if second[f] >= 0:
                idx += state[n, second[f]]
            area += lut[f, idx, 0]
            moment += lut[f, idx, 1]
        out[n] = moment / area if area > 0.0 else UNKNOWN_RISK
