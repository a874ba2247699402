"""Payeur's fuzzy inference engine: fuzzify a beam, fuse with Table 1, defuzzify to risk.

A cell's state is one activation per label, stored as ``uint8`` (255 = 1.0) in
``labels`` order, i.e. along the risk axis. Three vectorized steps:

- :meth:`FuzzyEngine.fuzzify` maps ``distance = cell position - measured range``
  (in units of the beam's sigma, eq. 5) to activations of the input membership
  functions;
- :meth:`FuzzyEngine.fuse` applies the rule table (Mamdani: a rule fires at
  AND(current, new), a label takes the OR of the rules concluding it);
- :meth:`FuzzyEngine.defuzzify` returns the centroid of the aggregated output set.

min and max commute with rounding to 1/255 steps (rounding is monotone), so with
the default operators fusion in ``uint8`` is exactly the quantised float result.
The product / probabilistic-sum options are computed in float per cell and
rounded once.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from fuzzyocc._engine_kernels import UNKNOWN_RISK, defuzzify_lut, fuse_rows, fuzzify_distances, pair_table
from fuzzyocc.membership import MembershipFunction, check_coverage, ladder

__all__ = [
    "PAPER_INPUT_PEAKS",
    "PAPER_LABELS",
    "PAPER_RULES",
    "RISK_SAMPLES",
    "FuzzyEngine",
    "even_output_mfs",
]

#: What :meth:`FuzzyEngine.fuzzifier` returns: ``(xs, ys, counts, rows, bounds)``.
Fuzzifier = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]

#: Labels of the paper in risk order (state and output order).
PAPER_LABELS: tuple[str, ...] = ("EMP", "MPE", "PE", "UNK", "PO", "MPO", "OCC")

#: Input peaks in sigmas along the distance axis for EMP MPE PE PO MPO OCC UNK (DESIGN.md section 4.1):
#: EMP's plateau ends at -5 and it reaches 0 at -4; OCC peaks on the surface; UNK is full from +1.5.
PAPER_INPUT_PEAKS: tuple[float, ...] = (-5.0, -4.0, -3.0, -2.0, -1.0, 0.0, 1.5)
_DISTANCE_ORDER: tuple[str, ...] = ("EMP", "MPE", "PE", "PO", "MPO", "OCC", "UNK")

#: Table 1 of the paper, ``PAPER_RULES[current][new]``; rows are input 2 (the cell's current state),
#: columns input 1 (the new measurement), both in the paper's column order (distance order).
PAPER_RULES: Mapping[str, Mapping[str, str]] = {
    current: dict(zip(_DISTANCE_ORDER, row))
    for current, row in zip(
        _DISTANCE_ORDER,
        (
            ("EMP", "MPE", "MPE", "MPE", "PE", "UNK", "EMP"),
            ("EMP", "MPE", "PE", "PE", "UNK", "PE", "MPE"),
            ("MPE", "MPE", "PE", "UNK", "PO", "PO", "PE"),
            ("PE", "PE", "UNK", "PO", "MPO", "MPO", "PO"),
            ("PO", "UNK", "PO", "PO", "MPO", "OCC", "MPO"),
            ("UNK", "PO", "PO", "MPO", "MPO", "OCC", "OCC"),
            ("MPE", "MPE", "PE", "PO", "MPO", "MPO", "UNK"),
        ),
    )
}

#: Samples of the risk axis [0, 1] the centroid is computed on (bin midpoints, symmetric about 0.5).
RISK_SAMPLES = 1000

#: Largest ``no_return_neighbours`` (beams on each side a no-return looks at).
MAX_NO_RETURN_NEIGHBOURS = 8

_AND_OPS = ("min", "product")
_OR_OPS = ("max", "probsum")


def even_output_mfs(labels: Sequence[str]) -> dict[str, MembershipFunction]:
    """Output membership functions evenly spaced on [0, 1]: shoulders at the ends, triangles between.

    Peaks sit at ``k / (L - 1)``, so a cell holding one label at full activation
    has a risk linear in the label's rank (the paper's "linear distribution"
    of risk, section III.C), mirror labels get mirror risks, and with an odd
    number of labels the middle one (UNK) is centred on 0.5. The end labels'
    plateaus lie outside [0, 1], so their centroid is ``1 / (3 (L - 1))`` from
    the end (1/18 for 7 labels, 1/30 for 11): a centroid never reaches 0 or 1 exactly.
    """
    n = len(labels)
    if n < 2:
        raise ValueError(f"labels needs at least 2 labels, got {n}")
    return dict(zip(labels, ladder([k / (n - 1) for k in range(n)])))


def _as_label_map(name: str, mfs: object) -> dict[str, MembershipFunction]:
    if isinstance(mfs, Mapping):
        items = list(mfs.items())
    else:
        try:
            items = [tuple(pair) for pair in mfs]  # type: ignore[union-attr]
        except TypeError:
            raise ValueError(f"{name} must be a mapping label -> membership function, got {mfs!r}") from None
        if any(len(pair) != 2 for pair in items):
            raise ValueError(f"{name} must be a mapping label -> membership function (or (label, mf) pairs)")
    out: dict[str, MembershipFunction] = {}
    for label, mf in items:
        if label in out:
            raise ValueError(f"{name} gives label {label!r} twice")
        if not isinstance(mf, MembershipFunction):
            raise ValueError(f"{name}[{label!r}] must be a MembershipFunction, got {type(mf).__name__}")
        out[label] = mf
    return out


def _check_names(name: str, given: Sequence[str], labels: tuple[str, ...]) -> None:
    missing = [lab for lab in labels if lab not in given]
    extra = [lab for lab in given if lab not in labels]
    if missing or extra:
        raise ValueError(
            f"{name} must name exactly the labels {list(labels)}; missing {missing}, not a label {extra}"
        )


def _risk_axis() -> np.ndarray:
    return (np.arange(RISK_SAMPLES, dtype=np.float64) + 0.5) / RISK_SAMPLES


@dataclass(frozen=True)
class FuzzyEngine:
    """Labels, membership functions, rule table and operators of a fuzzy occupancy model.

    Parameters
    ----------
    labels : tuple of str
        State and output labels in increasing order of risk (e.g. EMP MPE PE UNK PO MPO OCC).
    unknown : str
        The label of unknown space; a new map is this label at full activation.
    input_mfs : mapping str -> MembershipFunction
        One function per label on the distance axis, in units of the beam's sigma
        (negative = in front of the measured surface). Together they must cover
        the whole real line, and far enough behind the surface only ``unknown``
        may be active, at 1. Stored as ``(label, mf)`` pairs in ``labels`` order.
    output_mfs : mapping str -> MembershipFunction
        One function per label on the risk axis; they must cover [0, 1], each
        label alone must defuzzify to a larger risk than the label before it,
        and ``unknown`` alone to 0.5 (the project's "unknown" risk).
    rules : (L, L) sequence of sequences of str, or mapping of mappings
        ``rules[current][new]`` is the label concluded by the rule firing on the
        current state's label and the new measurement's label; rows and columns
        in ``labels`` order, or keyed by label. Stored as a tuple of tuples in
        ``labels`` order.
    and_op : {"min", "product"}
        Rule firing strength; also how an output function is cut at its label's
        activation (clipped for min, scaled for product).
    or_op : {"max", "probsum"}
        Combination of the rules concluding one label, and aggregation of the
        output functions before the centroid.
    normalize : bool or None
        Rescale every fused state so that its largest activation is 1 (height
        normalisation). ``None`` (default) means "when ``and_op`` is product":
        a product shrinks the activations at each fusion (a cell between two
        labels, at 0.5 and 0.5, halves every time), so without it a long-lived
        map drives cells near surfaces to all-zero states, i.e. unknown. With
        min, and input functions that leave some activation >= 0.5 everywhere
        (a ladder does), the largest activation never falls below
        min(its value, 0.5): the paper's min/max engine needs none and keeps
        the paper's semantics (and uint8 exactness).
    incidence_floor : float in (0, 1]
        How a beam's sigma grows where it meets a surface at a grazing angle: along the
        beam it is ``sigma / max(sin(incidence), incidence_floor)``, the incidence taken
        from the end points of the neighbouring beams of a LaserScan (see
        :meth:`fuzzyocc.scans.LaserScan.to_rays`). A pose error of a few centimetres
        across a wall is that many centimetres divided by the sine along a grazing beam,
        so such beams would otherwise read the wall's cells as free space in front of
        their surface and wear walls away. 1 (default) ignores the incidence (the paper).
    no_return_neighbours : int in [0, 8]
        A no-return beam of a LaserScan with a hit among its ``k`` neighbours on each side
        clears free space only up to the nearest of those hits (less
        :data:`fuzzyocc.scans.NO_RETURN_CUT_MARGIN_M`): most likely it met the same dark or
        glass surface they did and returned nothing, and clearing on to ``range_max`` would
        wear that surface (a wall) away. A no-return among no-returns clears on to
        ``range_max``, so an obstacle that leaves open space behind it is still cleared.
        0 (default): every no-return clears to ``range_max`` (the paper, REP 117).

    Raises
    ------
    ValueError
        Naming the field and what is wrong with it.
    """

    labels: tuple[str, ...]
    unknown: str
    input_mfs: tuple[tuple[str, MembershipFunction], ...]
    output_mfs: tuple[tuple[str, MembershipFunction], ...]
    rules: tuple[tuple[str, ...], ...]
    and_op: str = "min"
    or_op: str = "max"
    normalize: bool | None = None
    incidence_floor: float = 1.0
    no_return_neighbours: int = 0
    _rule_index: np.ndarray = field(init=False, repr=False, compare=False)
    _input_breakpoints: tuple[np.ndarray, np.ndarray, np.ndarray] = field(init=False, repr=False, compare=False)
    _input_ends: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False, compare=False)
    _occupied_extent: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        labels = self.labels
        if isinstance(labels, str) or not all(isinstance(lab, str) for lab in labels):
            raise ValueError(f"labels must be a sequence of label names, got {labels!r}")
        labels = tuple(labels)
        if len(labels) < 2:
            raise ValueError(f"labels needs at least 2 labels, got {list(labels)}")
        duplicates = sorted({lab for lab in labels if labels.count(lab) > 1})
        if duplicates:
            raise ValueError(f"labels must be distinct, {duplicates} appear more than once")
        if self.unknown not in labels:
            raise ValueError(f"unknown label {self.unknown!r} is not one of labels {list(labels)}")
        if self.and_op not in _AND_OPS:
            raise ValueError(f"and_op must be one of {list(_AND_OPS)}, got {self.and_op!r}")
        if self.or_op not in _OR_OPS:
            raise ValueError(f"or_op must be one of {list(_OR_OPS)}, got {self.or_op!r}")
        if self.normalize not in (None, True, False):
            raise ValueError(f"normalize must be True, False or None (automatic), got {self.normalize!r}")
        floor = self.incidence_floor
        if isinstance(floor, bool) or not isinstance(floor, (int, float)) or not 0.0 < floor <= 1.0:
            raise ValueError(f"incidence_floor must be a number in (0, 1], got {floor!r}")
        object.__setattr__(self, "incidence_floor", float(floor))
        k = self.no_return_neighbours
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k <= MAX_NO_RETURN_NEIGHBOURS:
            raise ValueError(f"no_return_neighbours must be an integer in [0, {MAX_NO_RETURN_NEIGHBOURS}], got {k!r}")

        inputs = _as_label_map("input_mfs", self.input_mfs)
        outputs = _as_label_map("output_mfs", self.output_mfs)
        _check_names("input_mfs", list(inputs), labels)
        _check_names("output_mfs", list(outputs), labels)
        rules = _rule_rows(self.rules, labels)
        _check_unknown_column(rules, labels, self.unknown)

        check_coverage(inputs.values(), -math.inf, math.inf, "input_mfs (distance axis, sigmas)")
        check_coverage(outputs.values(), 0.0, 1.0, "output_mfs (risk axis)")
        extent = _occupied_extent(inputs, self.unknown)
        _check_output_order(outputs, labels, self.unknown)

        object.__setattr__(self, "labels", labels)
        normalize = self.and_op == "product" if self.normalize is None else self.normalize
        object.__setattr__(self, "normalize", bool(normalize))
        object.__setattr__(self, "input_mfs", tuple((lab, inputs[lab]) for lab in labels))
        object.__setattr__(self, "output_mfs", tuple((lab, outputs[lab]) for lab in labels))
        object.__setattr__(self, "rules", rules)
        index = np.array([[labels.index(c) for c in row] for row in rules], dtype=np.int64)
        index.flags.writeable = False
        object.__setattr__(self, "_rule_index", index)
        table = _breakpoint_table([inputs[lab] for lab in labels])
        object.__setattr__(self, "_input_breakpoints", table)
        object.__setattr__(self, "_input_ends", _constant_rows(*table))
        object.__setattr__(self, "_occupied_extent", extent)

    # ---------------------------------------------------------------- construction
    @classmethod
    def paper(cls, and_op: str = "min", or_op: str = "max", normalize: bool | None = None) -> FuzzyEngine:
        """The paper's engine: Table 1, input functions of DESIGN.md section 4.1, even outputs.

        Inputs form a ladder (:func:`fuzzyocc.membership.ladder`) over
        :data:`PAPER_INPUT_PEAKS`: EMP a left shoulder ending at -4 sigma,
        triangles MPE, PE, PO, MPO peaking at -4, -3, -2, -1 sigma, OCC the
        triangle (-1, 0, +1.5), UNK rising from 0 to 1 over 0 .. +1.5 sigma.
        Outputs: :func:`even_output_mfs`.

        With these placements section IV of the paper is reproduced for every
        operator pair (``tests/fuzzyocc/test_paper_behaviour.py``, and
        ``python -m fuzzyocc.figures``): progressive refinement into unknown
        space, a contradictory measurement concluded after two merges rather
        than one, recovery of the original surface after two re-fusions with
        the occluded peak kept. After one contradictory merge 10 mm behind the
        surface (sigma 4 mm) the original surface falls from 0.944 to 0.750 (OCC
        meeting PO/MPO evidence) and the new one rises to 0.833 (UNK meeting OCC
        gives MPO): the new surface leads, at the risk of a surface seen once;
        after the second merge it is at 0.944 and the original at 0.583.
        """
        inputs = dict(zip(_DISTANCE_ORDER, ladder(PAPER_INPUT_PEAKS)))
        return cls(
            labels=PAPER_LABELS,
            unknown="UNK",
            input_mfs=inputs,  # type: ignore[arg-type]  # normalised in __post_init__
            output_mfs=even_output_mfs(PAPER_LABELS),  # type: ignore[arg-type]
            rules=PAPER_RULES,  # type: ignore[arg-type]
            and_op=and_op,
            or_op=or_op,
            normalize=normalize,
        )

    # ---------------------------------------------------------------- properties
    @property
    def num_labels(self) -> int:
        """L, the number of labels (bytes of state per cell)."""
        return len(self.labels)

    @property
    def unknown_index(self) -> int:
        """Column of the unknown label in states and fuzzified evidence."""
        return self.labels.index(self.unknown)

    @property
    def occupied_extent(self) -> float:
        """Distance behind the surface, in sigmas, past which :meth:`fuzzify` is pure unknown.

        Fusing pure-unknown evidence leaves a state unchanged (the unknown
        column of the rule table is checked to be the identity; with
        ``normalize`` the state is normalised, as every fused state is), so a
        beam need not update cells beyond it. 1.5 for the paper.
        """
        return self._occupied_extent

    def unknown_state(self) -> np.ndarray:
        """``(L,) uint8``: 255 on the unknown label, 0 elsewhere (the state of a never-observed cell)."""
        state = np.zeros(self.num_labels, dtype=np.uint8)
        state[self.unknown_index] = 255
        return state

    # ---------------------------------------------------------------- the three steps
    def fuzzify(self, distance_sigmas: np.ndarray) -> np.ndarray:
        """Activations of the input labels at the given distances.

        Parameters
        ----------
        distance_sigmas : (N,) float array
            ``(cell position - measured range) / sigma`` (eq. 5 in sigmas);
            ``-inf`` and ``+inf`` are allowed (far in front / far behind).

        Returns
        -------
        (N, L) uint8 array
            Columns in ``labels`` order, ``round(255 * membership)``. Below the
            first breakpoint of every input function (most cells of a beam lie
            far in front of its surface) and above the last, the row is a
            constant copied as is.

        Raises
        ------
        ValueError
            ``distance_sigmas`` is not 1-D or contains NaN.
        """
        d = np.asarray(distance_sigmas)
        if d.dtype not in (np.float32, np.float64):  # float32 widens exactly in the kernel: no copy needed
            d = d.astype(np.float64)
        if d.ndim != 1:
            raise ValueError(f"distance_sigmas must be 1-D (N,), got shape {d.shape}")
        out = np.empty((d.shape[0], self.num_labels), dtype=np.uint8)
        if fuzzify_distances(d, *self.fuzzifier(), out) >= 0:
            bad = int(np.flatnonzero(np.isnan(d))[0])
            raise ValueError(f"distance_sigmas must not contain NaN (first at index {bad})")
        return out

    def fuse(self, state: np.ndarray, evidence: np.ndarray) -> np.ndarray:
        """Merge new evidence into current states with the rule table (Mamdani inference).

        Parameters
        ----------
        state : (N, L) uint8 array
            Current states (input 2 of Table 1).
        evidence : (N, L) uint8 array
            Fuzzified new measurement for the same cells (input 1).

        Returns
        -------
        (N, L) uint8 array
            The next states; label k = OR over rules (i, j) concluding k of
            AND(state_i, evidence_j), rescaled to a largest activation of 255
            when ``normalize``. Inputs are not modified.

        Raises
        ------
        ValueError
            Wrong dtype or shape of ``state`` or ``evidence``.
        """
        state = self._check_states("state", state)
        evidence = self._check_states("evidence", evidence)
        if evidence.shape != state.shape:
            raise ValueError(f"evidence must have the shape of state {state.shape}, got {evidence.shape}")
        out = np.empty_like(state)
        fuse_rows(state, evidence, *self.row_fusion(), out)
        return out

    def fuzzifier(self) -> Fuzzifier:
        """``(xs, ys, counts, rows, bounds)``: what :func:`~fuzzyocc._engine_kernels.fuzzify_into` and
        :func:`~fuzzyocc._engine_kernels.evidence_class` take.

        For storage that fuzzifies in its own compiled loop (``fuzzyocc.grid.BlockGrid``), with
        the very arithmetic of :meth:`fuzzify`: ``xs, ys, counts`` are the input functions'
        breakpoints, ``rows`` (3, L) the constant rows of classes 0-2 and ``bounds`` their
        limits (see :func:`~fuzzyocc._engine_kernels.evidence_class`).
        """
        return (*self._input_breakpoints, *self._input_ends)

    def row_fusion(self) -> tuple[np.ndarray, tuple[bool, bool, bool] | None]:
        """``(rules, float_ops)``: the arguments :func:`~fuzzyocc._engine_kernels.fuse_row` takes for this engine.

        For storage that fuses rows in its own compiled loop (``fuzzyocc.grid.BlockGrid``)
        with the very arithmetic of :meth:`fuse`. ``float_ops`` is None for the exact uint8
        min/max fusion (a separate compiled specialisation), else ``(product, probsum, normalize)``.
        """
        if self._integer_fusion:
            return self._rule_index, None
        return self._rule_index, (self.and_op == "product", self.or_op == "probsum", bool(self.normalize))

    @property
    def _integer_fusion(self) -> bool:
        # min/max commute with the rounding to 1/255 steps: fusion in uint8 is exact.
        return self.and_op == "min" and self.or_op == "max" and not self.normalize

    def defuzzify(self, state: np.ndarray) -> np.ndarray:
        """Risk of each state: centroid of the aggregated output set.

        Each label's output function is cut at its activation (clipped for
        ``and_op="min"``, scaled for ``"product"``), the cuts are aggregated
        with ``or_op``, and the centroid is taken over :data:`RISK_SAMPLES`
        bin midpoints of [0, 1]. A state with every activation 0 has no output
        set; it is given 0.5 (unknown).

        Parameters
        ----------
        state : (N, L) uint8 array

        Returns
        -------
        (N,) float32 array in [0, 1]
        """
        state = self._check_states("state", state)
        tables = _defuzzify_tables(self)
        out = np.empty(state.shape[0], dtype=np.float32)
        if tables is None:
            _defuzzify_direct(self, state, out)
        else:
            first, second, lut = tables
            defuzzify_lut(state, first, second, lut, out)
        return out

    def _check_states(self, name: str, array: np.ndarray) -> np.ndarray:
        a = np.asarray(array)
        if a.dtype != np.uint8:
            raise ValueError(f"{name} must be uint8 activations (255 = 1.0), got dtype {a.dtype}")
        if a.ndim != 2 or a.shape[1] != self.num_labels:
            raise ValueError(f"{name} must have shape (N, {self.num_labels}), got {a.shape}")
        return np.ascontiguousarray(a)


# -------------------------------------------------------------------- validation helpers
def _rule_rows(rules: object, labels: tuple[str, ...]) -> tuple[tuple[str, ...], ...]:
    n = len(labels)
    if isinstance(rules, Mapping):
        _check_names("rules (rows)", list(rules), labels)
        rows: list[tuple[str, ...]] = []
        for current in labels:
            row = rules[current]
            if not isinstance(row, Mapping):
                raise ValueError(f"rules[{current!r}] must be a mapping new label -> conclusion")
            _check_names(f"rules[{current!r}] (columns)", list(row), labels)
            rows.append(tuple(row[new] for new in labels))
    else:
        if isinstance(rules, str) or not isinstance(rules, Sequence):
            raise ValueError(f"rules must be an {n} x {n} table of label names, got {type(rules).__name__}")
        rows = []
        for r, row in enumerate(rules):
            if isinstance(row, str) or not isinstance(row, Sequence):
                raise ValueError(f"rules row {r} must be a sequence of label names, got {row!r}")
            rows.append(tuple(row))
        widths = sorted({len(row) for row in rows})
        if len(rows) != n or widths != [n]:
            raise ValueError(
                f"rules must be an {n} x {n} table (one row and one column per label), "
                f"got {len(rows)} rows of lengths {widths}"
            )
    for r, row in enumerate(rows):
        for c, conclusion in enumerate(row):
            if conclusion not in labels:
                raise ValueError(
                    f"rules[{labels[r]!r}][{labels[c]!r}] concludes {conclusion!r}, which is not one of {list(labels)}"
                )
    return tuple(rows)


def _check_unknown_column(rules: tuple[tuple[str, ...], ...], labels: tuple[str, ...], unknown: str) -> None:
    # Maps stop a beam at occupied_extent: that is only right if unknown evidence changes nothing.
    u = labels.index(unknown)
    for r, row in enumerate(rules):
        if row[u] != labels[r]:
            raise ValueError(
                f"rules[{labels[r]!r}][{unknown!r}] concludes {row[u]!r}; the unknown column must be the identity "
                "(a measurement says nothing about the cells behind its surface, and maps do not update them)"
            )


def _occupied_extent(inputs: Mapping[str, MembershipFunction], unknown: str) -> float:
    extent = -math.inf
    for label, mf in inputs.items():
        if label == unknown:
            continue
        hi = mf.support[1]
        if math.isinf(hi):
            raise ValueError(
                f"input_mfs[{label!r}] is positive up to +inf; only the unknown label may be active "
                "arbitrarily far behind the surface"
            )
        extent = max(extent, hi)
    xs, ys = inputs[unknown].breakpoints
    if ys[-1] != 1.0:
        raise ValueError(f"input_mfs[{unknown!r}] (the unknown label) must reach 1 far behind the surface")
    full_from = next(xs[k] for k in range(len(ys)) if all(y == 1.0 for y in ys[k:]))
    return float(max(extent, full_from))


def _alone_centroids(outputs: Mapping[str, MembershipFunction], labels: Sequence[str]) -> list[float]:
    x = _risk_axis()
    centroids = []
    for lab in labels:
        mu = outputs[lab](x)
        area = mu.sum()
        centroids.append(float((x * mu).sum() / area) if area > 0 else math.nan)
    return centroids


def _check_output_order(outputs: Mapping[str, MembershipFunction], labels: tuple[str, ...], unknown: str) -> None:
    centroids = _alone_centroids(outputs, labels)
    for lab, c in zip(labels, centroids):
        if math.isnan(c):
            raise ValueError(f"output_mfs[{lab!r}] is 0 everywhere on the risk axis [0, 1]")
    for k in range(len(labels) - 1):
        if not centroids[k] < centroids[k + 1]:
            raise ValueError(
                f"output_mfs must follow labels in increasing risk: {labels[k]!r} alone defuzzifies to "
                f"{centroids[k]:.4f}, not below {labels[k + 1]!r} at {centroids[k + 1]:.4f}"
            )
    c_unknown = centroids[labels.index(unknown)]
    if abs(c_unknown - UNKNOWN_RISK) > 1e-3:
        raise ValueError(
            f"output_mfs[{unknown!r}] (the unknown label) must be centred on risk 0.5, its centroid is {c_unknown:.4f}"
        )


# -------------------------------------------------------------------- precomputed tables
def _breakpoint_table(mfs: Sequence[MembershipFunction]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Breakpoints ``(xs, ys)`` of every function padded to a common width, and how many each has."""
    points = [mf.breakpoints for mf in mfs]
    width = max(len(px) for px, _ in points)
    xs, ys = np.zeros((len(points), width)), np.zeros((len(points), width))
    counts = np.array([len(px) for px, _ in points], dtype=np.int64)
    for k, (px, py) in enumerate(points):
        xs[k, : len(px)], ys[k, : len(py)] = px, py
    for a in (xs, ys, counts):
        a.flags.writeable = False
    return xs, ys, counts


def _cut(mu: np.ndarray, activation: np.ndarray, and_op: str) -> np.ndarray:
    return mu * activation if and_op == "product" else np.minimum(mu, activation)


def _aggregate(a: np.ndarray, b: np.ndarray, or_op: str) -> np.ndarray:
    return a + b - a * b if or_op == "probsum" else np.maximum(a, b)


@functools.lru_cache(maxsize=16)
def _defuzzify_tables(engine: FuzzyEngine) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Area and moment of the output set, tabulated per pair of overlapping labels.

    When at most two output functions are positive at every sample of the risk
    axis, the aggregated set on the samples where only labels {i, j} are
    positive depends on (activation_i, activation_j) alone, for any operator
    pair (OR with 0 is the identity). Grouping the samples by such pairs gives
    ``area = sum_f A_f[a_i, a_j]``, ``moment = sum_f M_f[a_i, a_j]`` over a few
    65536-entry tables: exact for the discretised definition, a handful of
    lookups per cell. Returns None when three functions overlap somewhere.
    """
    x = _risk_axis()
    mu = np.stack([mf(x) for _, mf in engine.output_mfs])  # (L, M)
    positive = mu > 0.0
    if positive.sum(axis=0).max() > 2:
        return None
    # Each sample goes to one factor (i, j): its pair of positive labels, or for a sample where one
    # label i is positive, any pair containing i (fewer lookups), else the single (i, -1).
    supports = [tuple(np.flatnonzero(positive[:, m])) for m in range(x.size)]
    pairs = sorted({s for s in supports if len(s) == 2})
    singles = sorted({s[0] for s in supports if len(s) == 1} - {i for p in pairs for i in p})
    factors = [(int(i), int(j)) for i, j in pairs] + [(int(i), -1) for i in singles]

    def owner(support: tuple[int, ...]) -> int:
        return next(f for f, pair in enumerate(factors) if set(support) <= set(pair))

    sample_factor = np.array([owner(s) if s else -1 for s in supports])
    lut = np.empty((len(factors), 256, 256, 2))
    product, probsum = engine.and_op == "product", engine.or_op == "probsum"
    for f, (i, j) in enumerate(factors):
        cols = np.flatnonzero(sample_factor == f)
        mu_j = mu[j, cols] if j >= 0 else np.zeros(cols.size)
        pair_table(mu[i, cols], mu_j, x[cols], product, probsum, lut[f])
    lut = lut.reshape(len(factors), 256 * 256, 2)
    first = np.array([i for i, _ in factors], dtype=np.int64)
    second = np.array([j for _, j in factors], dtype=np.int64)
    return first, second, lut


def _defuzzify_direct(engine: FuzzyEngine, state: np.ndarray, out: np.ndarray, chunk: int = 4096) -> None:
    """The definition evaluated on every risk sample, chunk by chunk (any overlap of output functions)."""
    x = _risk_axis()
    mu = np.stack([mf(x) for _, mf in engine.output_mfs])
    for start in range(0, state.shape[0], chunk):
        act = state[start : start + chunk].astype(np.float64) / 255.0
        agg = np.zeros((act.shape[0], x.size))
        for k in range(mu.shape[0]):
            agg = _aggregate(agg, _cut(mu[k][None, :], act[:, k : k + 1], engine.and_op), engine.or_op)
        area = agg.sum(axis=1)
        moment = agg @ x
        safe = np.where(area > 0.0, area, 1.0)
        out[start : start + chunk] = np.where(area > 0.0, moment / safe, UNKNOWN_RISK)


def _constant_rows(xs: np.ndarray, ys: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, bounds)`` for :func:`~fuzzyocc._engine_kernels.evidence_class`: the rows at -inf, at +inf and on the flat interval.

    Strictly below ``bounds[0]`` every function is at its first breakpoint's value and
    strictly above ``bounds[1]`` at its last one's; on ``(bounds[2], bounds[3])``, the widest
    gap between consecutive breakpoints (of all functions) over which every function is
    constant, they hold the flat row (``bounds[2] > bounds[3]``: there is none). The rows
    are computed by the kernel itself with every distance sloped, so the rounding is the same.
    """
    low = float(xs[:, 0].min())
    high = float(max(xs[k, c - 1] for k, c in enumerate(counts)))
    points = np.unique(np.concatenate([xs[k, :c] for k, c in enumerate(counts)]))
    samples = np.concatenate([[-np.inf, np.inf], points])
    every_sloped = np.array([-np.inf, np.inf, np.inf, -np.inf])
    unused = np.zeros((3, xs.shape[0]), dtype=np.uint8)
    for a in (every_sloped, unused):
        a.flags.writeable = False  # the type the real ones have: one compiled specialisation, not two
    at = np.empty((samples.size, xs.shape[0]), dtype=np.uint8)
    fuzzify_distances(samples, xs, ys, counts, unused, every_sloped, at)
    flat_lo, flat_hi, flat_row = np.inf, -np.inf, unused[0]
    exact = [np.array([np.interp(x, xs[k, :c], ys[k, :c]) for k, c in enumerate(counts)]) for x in points]
    for i in range(points.size - 1):  # between consecutive breakpoints every function is linear
        if np.array_equal(exact[i], exact[i + 1]) and points[i + 1] - points[i] > flat_hi - flat_lo:
            flat_lo, flat_hi, flat_row = float(points[i]), float(points[i + 1]), at[2 + i]
    rows = np.stack([at[0], at[1], flat_row])
    bounds = np.array([low, high, flat_lo, flat_hi])
    for a in (rows, bounds):
        a.flags.writeable = False
    return rows, bounds
