"""The paper's n-input merge: a cell's state fused with n measurements at once.

Section III of the paper: "this table of rules can also be extended to n dimensions in order
to allow a simultaneous merge of n fuzzy inputs". The n-dimensional table is built from the
engine's own 2-D table: the label concluded from the current label ``i`` and new labels
``j_1 .. j_n`` is the 2-D table applied to them in a canonical order (the new labels sorted by
their rank, emptiest first), so the result does not depend on the order in which the n inputs
arrive. Mamdani inference as in :meth:`FuzzyEngine.fuse`: a rule fires at the AND (min) of its
n + 1 antecedents, a label takes the OR (max) of the rules concluding it. For an additive
table (``fuzzyocc.evidence``: conclusion = current level + a step per new label, clamped at
each step) the free readings come first in that order, so at the empty end they are clamped
before the hits are added: the merge leans towards occupied there (E5 with one free reading
and one hit gives E3, where summing first would give E4).

Used by ``bench/bench_maps.py`` to merge all beams of one scan that reach a cell at once,
instead of the ray caster's "most occupied-ward beam wins"; the bench prints both (the default
stays with the latter: see ``docs/DESIGN.md`` for the figures).
"""

from __future__ import annotations

import numba
import numpy as np

from fuzzyocc.engine import FuzzyEngine

__all__ = ["merge_n"]

#: Inputs merged at once at most; beyond it a group's first rows are dropped (order the rows so
#: that the last ones matter most). Up to 2**n label combinations are enumerated per cell.
MAX_INPUTS = 12


def merge_n(engine: FuzzyEngine, state: np.ndarray, evidence: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Fuse each state with its group of evidence rows at once (min/max engines only).

    Parameters
    ----------
    engine : FuzzyEngine
        With ``and_op="min"`` and ``or_op="max"`` (no normalisation).
    state : (G, L) uint8 array
        The current state of each of G cells.
    evidence : (M, L) uint8 array
        Fuzzified measurements, the rows of cell g being ``evidence[groups[g]:groups[g + 1]]``.
    groups : (G + 1,) int array
        Offsets of each cell's rows, non-decreasing, from 0 to M.

    Returns
    -------
    (G, L) uint8 array
        The merged states. A cell with no evidence keeps its state.
    """
    if engine.and_op != "min" or engine.or_op != "max" or engine.normalize:
        raise ValueError("merge_n needs a min/max engine without normalisation")
    if _most_inputs_positive(engine) > 2:
        raise ValueError("merge_n needs input functions of which at most two are positive at any distance")
    state = np.ascontiguousarray(state, dtype=np.uint8)
    evidence = np.ascontiguousarray(evidence, dtype=np.uint8)
    groups = np.ascontiguousarray(groups, dtype=np.int64)
    if state.ndim != 2 or evidence.ndim != 2 or state.shape[1] != engine.num_labels != evidence.shape[1]:
        raise ValueError(f"state and evidence must have shape (., {engine.num_labels})")
    if groups.shape != (state.shape[0] + 1,) or groups[0] != 0 or groups[-1] != evidence.shape[0]:
        raise ValueError("groups must hold G + 1 offsets from 0 to the number of evidence rows")
    if np.any(np.diff(groups) < 0):
        raise ValueError("groups must be non-decreasing")
    rules = np.asarray(engine.row_fusion()[0], dtype=np.int64)
    out = np.empty_like(state)
    _merge(state, evidence, groups, rules, MAX_INPUTS, out)
    return out


def _most_inputs_positive(engine: FuzzyEngine) -> int:
    """The largest number of input functions positive at one distance (between breakpoints it is constant)."""
    points = np.unique(np.concatenate([mf.breakpoints[0] for _, mf in engine.input_mfs]))
    probes = np.concatenate([points, 0.5 * (points[1:] + points[:-1]), [points[0] - 1.0, points[-1] + 1.0]])
    return int(max(np.sum([mf(probes) > 0.0 for _, mf in engine.input_mfs], axis=0)))


@numba.njit(cache=True, nogil=True)
def _merge(state, evidence, groups, rules, max_inputs, out):  # pragma: no cover - compiled
    n_labels = state.shape[1]
    labels = np.empty((max_inputs, 2), np.int64)
    acts = np.empty((max_inputs, 2), np.uint8)
    counts = np.empty(max_inputs, np.int64)
    chosen = np.empty(max_inputs, np.int64)
    for g in range(state.shape[0]):
        lo, hi = groups[g], groups[g + 1]
        n = min(hi - lo, max_inputs)
        first = hi - n
        for q in range(n):  # each input's active labels (at most two for ladder inputs; the largest two kept)
            row = first + q
            counts[q] = 0
            for k in range(n_labels):
                a = evidence[row, k]
                if a == 0:
                    continue
                if counts[q] < 2:
                    labels[q, counts[q]] = k
                    acts[q, counts[q]] = a
                    counts[q] += 1
                elif a > min(acts[q, 0], acts[q, 1]):
                    w = 0 if acts[q, 0] < acts[q, 1] else 1
                    labels[q, w] = k
                    acts[q, w] = a
        for k in range(n_labels):
            out[g, k] = 0
        if n == 0:
            for k in range(n_labels):
                out[g, k] = state[g, k]
            continue
        total = 1
        for q in range(n):
            total *= max(counts[q], 1)
        for combo in range(total):
            c = combo
            strength = 255
            for q in range(n):
                m = max(counts[q], 1)
                pick = c % m
                c //= m
                if counts[q] == 0:
                    chosen[q] = -1
                    continue
                chosen[q] = labels[q, pick]
                strength = min(strength, acts[q, pick])
            if strength == 0:
                continue
            # the canonical order: new labels by rank, emptiest first (insertion sort of n <= 12)
            for q in range(1, n):
                v = chosen[q]
                p = q - 1
                while p >= 0 and chosen[p] > v:
                    chosen[p + 1] = chosen[p]
                    p -= 1
                chosen[p + 1] = v
            for i in range(n_labels):
                s = state[g, i]
                if s == 0:
                    continue
                fire = min(s, strength)
                concl = i
                for q in range(n):
                    if chosen[q] >= 0:
                        concl = rules[concl, chosen[q]]
                if fire > out[g, concl]:
                    out[g, concl] = fire
    return out
