import dataclasses

import numpy as np
import pytest

from fuzzyocc.engine import (
    PAPER_INPUT_PEAKS,
    PAPER_LABELS,
    PAPER_RULES,
    FuzzyEngine,
    _defuzzify_direct,
    even_output_mfs,
)
from fuzzyocc.membership import MembershipFunction, RightShoulder, Triangle, ladder

OPERATORS = [("min", "max"), ("product", "max"), ("min", "probsum"), ("product", "probsum")]
DISTANCE_ORDER = ("EMP", "MPE", "PE", "PO", "MPO", "OCC", "UNK")


def paper_parts() -> dict:
    """Keyword arguments of the paper's engine, for tests that break one of them."""
    return {
        "labels": PAPER_LABELS,
        "unknown": "UNK",
        "input_mfs": dict(zip(DISTANCE_ORDER, ladder(PAPER_INPUT_PEAKS))),
        "output_mfs": even_output_mfs(PAPER_LABELS),
        "rules": {cur: dict(row) for cur, row in PAPER_RULES.items()},
    }


def state(engine: FuzzyEngine, **activations: int) -> np.ndarray:
    """One cell's (1, L) uint8 state from label=activation pairs."""
    s = np.zeros((1, engine.num_labels), dtype=np.uint8)
    for label, value in activations.items():
        s[0, engine.labels.index(label)] = value
    return s


def random_states(engine: FuzzyEngine, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = rng.integers(0, 256, (n, engine.num_labels), dtype=np.uint8)
    s[rng.random(s.shape) < 0.6] = 0  # real states are sparse
    return s


# ---------------------------------------------------------------- the paper's engine
def test_paper_engine_shape_and_unknown_state() -> None:
    e = FuzzyEngine.paper()
    assert e.labels == ("EMP", "MPE", "PE", "UNK", "PO", "MPO", "OCC")
    assert e.num_labels == 7
    assert e.occupied_extent == 1.5
    np.testing.assert_array_equal(e.unknown_state(), [0, 0, 0, 255, 0, 0, 0])
    assert e.unknown_state().dtype == np.uint8


def test_table1_transcription_spot_checks() -> None:
    # Read off the paper's Table 1: rows are the current state (input 2), columns the new measurement.
    assert PAPER_RULES["EMP"]["EMP"] == "EMP"
    assert PAPER_RULES["EMP"]["MPO"] == "PE"
    assert PAPER_RULES["MPE"]["OCC"] == "PE"
    assert PAPER_RULES["PE"]["MPO"] == "PO"
    assert PAPER_RULES["PO"]["EMP"] == "PE"
    assert PAPER_RULES["MPO"]["OCC"] == "OCC"
    assert PAPER_RULES["OCC"]["MPE"] == "PO"
    assert PAPER_RULES["UNK"]["EMP"] == "MPE"
    assert PAPER_RULES["UNK"]["OCC"] == "MPO"


def test_table1_opposite_labels_conclude_unknown() -> None:
    # The anti-diagonal of Table 1: a measurement opposite to the state cancels it into UNK.
    for current, new in zip(DISTANCE_ORDER[:6], reversed(DISTANCE_ORDER[:6])):
        assert PAPER_RULES[current][new] == "UNK", (current, new)


def test_table1_is_not_symmetric() -> None:
    # The paper insists the new input must weigh differently from the current state.
    assert PAPER_RULES["UNK"]["EMP"] != PAPER_RULES["EMP"]["UNK"]
    assert PAPER_RULES["MPE"]["OCC"] != PAPER_RULES["OCC"]["MPE"]


def test_table1_unknown_column_is_the_identity() -> None:
    e = FuzzyEngine.paper()
    u = e.labels.index("UNK")
    assert [row[u] for row in e.rules] == list(e.labels)


def test_rules_are_stored_in_labels_order() -> None:
    e = FuzzyEngine.paper()
    L = e.labels.index
    assert e.rules[L("EMP")][L("OCC")] == "UNK"
    assert e.rules[L("UNK")][L("MPE")] == "MPE"


def test_rules_as_nested_lists_equal_rules_as_mappings() -> None:
    parts = paper_parts()
    table = [[parts["rules"][cur][new] for new in PAPER_LABELS] for cur in PAPER_LABELS]
    assert FuzzyEngine(**{**parts, "rules": table}) == FuzzyEngine.paper()


def test_empty_batches_pass_through_all_three_steps() -> None:
    e = FuzzyEngine.paper()
    evidence = e.fuzzify(np.empty(0))
    assert evidence.shape == (0, 7) and evidence.dtype == np.uint8
    assert e.fuse(evidence, evidence).shape == (0, 7)
    assert e.defuzzify(evidence).shape == (0,)


# ---------------------------------------------------------------- fuzzify
def test_fuzzify_columns_follow_labels_not_distance_order() -> None:
    e = FuzzyEngine.paper()
    out = e.fuzzify(np.array([0.0, 1.5, -np.inf, -3.0]))
    np.testing.assert_array_equal(out[0], state(e, OCC=255)[0])
    np.testing.assert_array_equal(out[1], state(e, UNK=255)[0])
    np.testing.assert_array_equal(out[2], state(e, EMP=255)[0])
    np.testing.assert_array_equal(out[3], state(e, PE=255)[0])


def test_fuzzify_interpolates_between_neighbouring_peaks() -> None:
    e = FuzzyEngine.paper()
    # Half way between MPO's peak (-1) and OCC's (0); 0.75 is half way down OCC's right side.
    np.testing.assert_array_equal(e.fuzzify(np.array([-0.5]))[0], state(e, MPO=128, OCC=128)[0])
    np.testing.assert_array_equal(e.fuzzify(np.array([0.75]))[0], state(e, OCC=128, UNK=128)[0])


def test_fuzzify_is_each_input_function_rounded_to_uint8() -> None:
    e = FuzzyEngine.paper()
    d = np.concatenate([np.random.default_rng(2).uniform(-9.0, 3.0, 20_000), np.array(PAPER_INPUT_PEAKS)])
    out = e.fuzzify(d)
    for k, (label, mf) in enumerate(e.input_mfs):
        assert label == e.labels[k]
        np.testing.assert_array_equal(out[:, k], np.floor(mf(d) * 255 + 0.5).astype(np.uint8), err_msg=label)


def test_fuzzify_is_a_partition_up_to_rounding() -> None:
    e = FuzzyEngine.paper()
    out = e.fuzzify(np.random.default_rng(1).uniform(-8.0, 4.0, 50_000)).astype(int)
    assert np.abs(out.sum(axis=1) - 255).max() <= 1


def test_fuzzify_is_pure_unknown_beyond_the_occupied_extent() -> None:
    e = FuzzyEngine.paper()
    far = e.fuzzify(np.linspace(e.occupied_extent, 1e6, 1000))
    assert (far == e.unknown_state()).all()
    assert not (e.fuzzify(np.array([e.occupied_extent - 0.05])) == e.unknown_state()).all()


def test_fuzzify_refuses_nan_and_non_vectors() -> None:
    e = FuzzyEngine.paper()
    with pytest.raises(ValueError, match=r"distance_sigmas .*NaN.*index 2"):
        e.fuzzify(np.array([0.0, 1.0, np.nan]))
    with pytest.raises(ValueError, match="distance_sigmas must be 1-D"):
        e.fuzzify(np.zeros((2, 2)))


# ---------------------------------------------------------------- fuse
def test_fuse_min_max_by_hand() -> None:
    e = FuzzyEngine.paper()
    current = state(e, MPO=200, UNK=100)
    new = state(e, OCC=128, UNK=127)
    # MPO x OCC -> OCC at min(200, 128); MPO x UNK -> MPO at 127; UNK x OCC -> MPO at 100;
    # UNK x UNK -> UNK at 100. MPO takes the max of its two rules.
    np.testing.assert_array_equal(e.fuse(current, new), state(e, OCC=128, MPO=127, UNK=100))


def test_fuse_product_and_probsum_by_hand() -> None:
    for and_op, or_op in OPERATORS[1:]:
        e = FuzzyEngine.paper(and_op, or_op, normalize=False)
        current = state(e, MPO=200, UNK=100)
        new = state(e, OCC=128, UNK=127)
        a = (lambda x, y: x * y) if and_op == "product" else min
        o = (lambda x, y: x + y - x * y) if or_op == "probsum" else max
        s, n = {"MPO": 200 / 255, "UNK": 100 / 255}, {"OCC": 128 / 255, "UNK": 127 / 255}
        expected = {
            "OCC": a(s["MPO"], n["OCC"]),
            "MPO": o(a(s["MPO"], n["UNK"]), a(s["UNK"], n["OCC"])),
            "UNK": a(s["UNK"], n["UNK"]),
        }
        want = state(e, **{k: int(np.floor(v * 255 + 0.5)) for k, v in expected.items()})
        np.testing.assert_array_equal(e.fuse(current, new), want, err_msg=f"{and_op}/{or_op}")


@pytest.mark.parametrize(("and_op", "or_op"), OPERATORS)
def test_fusing_pure_unknown_evidence_changes_nothing(and_op: str, or_op: str) -> None:
    e = FuzzyEngine.paper(and_op, or_op)
    current = random_states(e, 5000)
    if e.normalize:  # states of a normalising engine are normalised (the unknown state is)
        current = e.fuse(current, np.tile(e.unknown_state(), (5000, 1)))
    evidence = np.tile(e.unknown_state(), (5000, 1))
    np.testing.assert_array_equal(e.fuse(current, evidence), current)


def test_product_is_height_normalised_so_repeated_fusion_does_not_fade() -> None:
    between = np.array([-0.5, -2.5, 0.75])  # cells half way between two input labels
    for normalize, fades in ((None, False), (False, True)):
        e = FuzzyEngine.paper("product", normalize=normalize)
        evidence = e.fuzzify(between)
        s = np.tile(e.unknown_state(), (3, 1))
        for _ in range(12):  # each fusion multiplies activations by about 0.5 without normalisation
            s = e.fuse(s, evidence)
        assert (s.max(axis=1) <= 1).all() if fades else (s.max(axis=1) == 255).all()
    assert FuzzyEngine.paper("product").normalize and not FuzzyEngine.paper().normalize


def test_fuse_leaves_its_inputs_alone() -> None:
    e = FuzzyEngine.paper()
    current, evidence = random_states(e, 100, 1), random_states(e, 100, 2)
    before = current.copy(), evidence.copy()
    e.fuse(current, evidence)
    np.testing.assert_array_equal(current, before[0])
    np.testing.assert_array_equal(evidence, before[1])


def test_min_max_fusion_in_uint8_equals_the_float_computation() -> None:
    e = FuzzyEngine.paper()
    current, evidence = random_states(e, 2000, 3), random_states(e, 2000, 4)
    s, n = current / 255.0, evidence / 255.0
    want = np.zeros_like(s)
    for i in range(7):
        for j in range(7):
            k = e.labels.index(e.rules[i][j])
            want[:, k] = np.maximum(want[:, k], np.minimum(s[:, i], n[:, j]))
    np.testing.assert_array_equal(e.fuse(current, evidence), np.round(want * 255).astype(np.uint8))


def test_fuse_refuses_wrong_dtype_and_shapes() -> None:
    e = FuzzyEngine.paper()
    good = np.zeros((3, 7), dtype=np.uint8)
    with pytest.raises(ValueError, match="state must be uint8"):
        e.fuse(good.astype(np.float32), good)
    with pytest.raises(ValueError, match=r"evidence must have shape \(N, 7\)"):
        e.fuse(good, np.zeros((3, 6), dtype=np.uint8))
    with pytest.raises(ValueError, match="evidence must have the shape of state"):
        e.fuse(good, np.zeros((2, 7), dtype=np.uint8))


# ---------------------------------------------------------------- defuzzify
def test_unknown_and_empty_states_defuzzify_to_one_half() -> None:
    e = FuzzyEngine.paper()
    risk = e.defuzzify(np.stack([e.unknown_state(), np.zeros(7, np.uint8)]))
    assert risk.dtype == np.float32
    np.testing.assert_allclose(risk, 0.5, atol=1e-6)


def test_single_labels_defuzzify_in_increasing_mirror_symmetric_risk() -> None:
    e = FuzzyEngine.paper()
    risk = e.defuzzify(np.eye(7, dtype=np.uint8) * 255)
    assert (np.diff(risk) > 0).all()
    np.testing.assert_allclose(risk + risk[::-1], 1.0, atol=1e-6)
    # Middle labels are symmetric triangles: their centroid is their peak, k/6.
    np.testing.assert_allclose(risk[1:6], np.arange(1, 6) / 6, atol=1e-6)
    # EMP on [0, 1] is the half triangle falling from 1 at 0 to 0 at 1/6: centroid 1/18.
    np.testing.assert_allclose(risk[0], 1 / 18, atol=1e-4)


def test_clipping_a_symmetric_label_keeps_its_centroid() -> None:
    e = FuzzyEngine.paper()
    cells = np.zeros((5, 7), dtype=np.uint8)
    cells[:, e.labels.index("MPO")] = [1, 50, 128, 200, 255]
    np.testing.assert_allclose(e.defuzzify(cells), 5 / 6, atol=1e-4)  # 1e-4: the risk axis is sampled


def test_more_occupied_evidence_raises_the_risk() -> None:
    e = FuzzyEngine.paper()
    cells = np.zeros((4, 7), dtype=np.uint8)
    cells[:, e.labels.index("MPO")] = 255
    cells[:, e.labels.index("OCC")] = [0, 60, 120, 255]
    assert (np.diff(e.defuzzify(cells)) > 0).all()


@pytest.mark.parametrize(("and_op", "or_op"), OPERATORS)
def test_fast_defuzzify_matches_the_definition(and_op: str, or_op: str) -> None:
    e = FuzzyEngine.paper(and_op, or_op)
    cells = random_states(e, 1000, 5)
    reference = np.empty(1000, dtype=np.float32)
    _defuzzify_direct(e, cells, reference)
    np.testing.assert_allclose(e.defuzzify(cells), reference, atol=1e-6)


def test_defuzzify_with_overlapping_outputs_uses_the_definition() -> None:
    # Three output functions overlap around 0.5: no pairwise table, same definition.
    parts = paper_parts()
    outputs = dict(even_output_mfs(PAPER_LABELS))
    outputs["UNK"] = Triangle(0.2, 0.5, 0.8)
    e = FuzzyEngine(**{**parts, "output_mfs": outputs})
    cells = np.zeros((2, 7), dtype=np.uint8)
    cells[0, e.labels.index("UNK")] = 255
    cells[1, [e.labels.index("PE"), e.labels.index("PO")]] = 255
    np.testing.assert_allclose(e.defuzzify(cells), [0.5, 0.5], atol=1e-6)


# ---------------------------------------------------------------- a larger label set
NINE = ("EMP", "MPE", "PE", "SE", "UNK", "SO", "PO", "MPO", "OCC")


def nine_label_engine() -> FuzzyEngine:
    """The paper's "larger number of members": 9 labels, a rule that moves one label at a time.

    Inputs: a ladder over EMP MPE PE SE SO PO MPO OCC UNK at -7 .. 0 sigma, UNK full from +1.5.
    Rules: the state steps one label (on the risk axis) toward the new measurement's label;
    an unknown measurement leaves it alone.
    """
    distance_order = ("EMP", "MPE", "PE", "SE", "SO", "PO", "MPO", "OCC", "UNK")
    peaks = (-7.0, -6.0, -5.0, -4.0, -3.0, -2.0, -1.0, 0.0, 1.5)
    rules = [
        [cur if new == "UNK" else NINE[NINE.index(cur) + int(np.sign(NINE.index(new) - NINE.index(cur)))]
         for new in NINE]
        for cur in NINE
    ]
    return FuzzyEngine(NINE, "UNK", dict(zip(distance_order, ladder(peaks))), even_output_mfs(NINE), rules)


@pytest.mark.parametrize("make", [FuzzyEngine.paper, nine_label_engine])
def test_fuzzify_rounds_each_function_everywhere_including_far_from_the_surface(make) -> None:
    e = make()
    xs = np.concatenate([np.array(mf.breakpoints[0]) for _, mf in e.input_mfs])
    d = np.concatenate([
        np.random.default_rng(3).uniform(-12.0, 4.0, 20_000),
        xs, np.nextafter(xs, -np.inf), np.nextafter(xs, np.inf),  # on and either side of every breakpoint
        [-np.inf, -1e6, 1e6, np.inf],
    ])
    out = e.fuzzify(d)
    for k, (_, mf) in enumerate(e.input_mfs):
        np.testing.assert_array_equal(out[:, k], np.floor(mf(d) * 255 + 0.5).astype(np.uint8), err_msg=e.labels[k])
    single = d.astype(np.float32)
    np.testing.assert_array_equal(e.fuzzify(single), e.fuzzify(single.astype(np.float64)))


def fusions_until_empty(engine: FuzzyEngine) -> int:
    s = engine.unknown_state()[None, :]
    evidence = engine.fuzzify(np.array([-np.inf]))  # far in front of the surface: pure EMP
    floor = engine.defuzzify(state(engine, EMP=255))[0]
    for k in range(1, 20):
        s = engine.fuse(s, evidence)
        if engine.defuzzify(s)[0] <= floor + 1e-6:
            return k
    raise AssertionError("never reached EMP")


def test_nine_labels_need_more_consistent_data_to_conclude() -> None:
    nine = nine_label_engine()
    assert nine.num_labels == 9 and nine.occupied_extent == 1.5
    np.testing.assert_allclose(nine.defuzzify(nine.unknown_state()[None, :]), 0.5, atol=1e-6)
    # UNK -> SE -> PE -> MPE -> EMP, against UNK -> MPE -> EMP for Table 1.
    assert fusions_until_empty(nine) == 4
    assert fusions_until_empty(FuzzyEngine.paper()) == 2


# ---------------------------------------------------------------- validation
def broken(**change: object) -> dict:
    return {**paper_parts(), **change}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"labels": ("EMP", "MPE", "PE", "UNK", "PO", "MPO", "MPO")}, r"labels must be distinct, \['MPO'\]"),
        ({"unknown": "UNKNOWN"}, "unknown label 'UNKNOWN' is not one of labels"),
        ({"and_op": "max"}, "and_op must be one of"),
        ({"or_op": "sum"}, "or_op must be one of"),
        ({"normalize": "yes"}, "normalize must be True, False or None"),
        ({"rules": [["EMP"] * 7] * 6}, r"rules must be an 7 x 7 table .* 6 rows"),
        ({"rules": [["EMP"] * 7] * 6 + [["EMP"] * 6]}, r"rows of lengths \[6, 7\]"),
        ({"rules": [["EMP"] * 7] * 3 + [["EMP"] * 3 + ["FOO"] + ["EMP"] * 3] + [["EMP"] * 7] * 3},
         r"rules\['UNK'\]\['UNK'\] concludes 'FOO'"),
        ({"rules": [["EMP"] * 7] * 7}, r"rules\['MPE'\]\['UNK'\] concludes 'EMP'; the unknown column must be"),
    ],
)
def test_engine_refuses_bad_tables_and_names(change: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        FuzzyEngine(**broken(**change))


def test_engine_refuses_mfs_for_the_wrong_labels() -> None:
    inputs = dict(paper_parts()["input_mfs"])
    inputs["OCCUPIED"] = inputs.pop("OCC")
    with pytest.raises(ValueError, match=r"input_mfs .* missing \['OCC'\], not a label \['OCCUPIED'\]"):
        FuzzyEngine(**broken(input_mfs=inputs))
    outputs = dict(paper_parts()["output_mfs"])
    del outputs["PE"]
    with pytest.raises(ValueError, match=r"output_mfs must name exactly .* missing \['PE'\]"):
        FuzzyEngine(**broken(output_mfs=outputs))


def test_engine_refuses_rule_mapping_with_missing_column() -> None:
    rules = paper_parts()["rules"]
    del rules["MPE"]["PO"]
    with pytest.raises(ValueError, match=r"rules\['MPE'\] \(columns\) must name exactly .* missing \['PO'\]"):
        FuzzyEngine(**broken(rules=rules))


def test_engine_refuses_input_mfs_leaving_a_gap() -> None:
    inputs = dict(paper_parts()["input_mfs"])
    inputs["MPE"] = Triangle(-5.0, -4.5, -4.0)  # nothing is positive from -4 (EMP's end) to -3 (PO's start)
    inputs["PE"] = Triangle(-3.0, -2.5, -2.0)
    with pytest.raises(ValueError, match=r"input_mfs \(distance axis, sigmas\) do not cover .* \[-4, -3\]$"):
        FuzzyEngine(**broken(input_mfs=inputs))


def test_engine_refuses_output_mfs_not_covering_the_risk_axis() -> None:
    outputs = dict(paper_parts()["output_mfs"])
    outputs["EMP"] = Triangle(0.05, 0.1, 1 / 6)  # MPE's open support (0, 1/3) covers all but x = 0
    with pytest.raises(ValueError, match=r"output_mfs \(risk axis\) do not cover .* at x = 0$"):
        FuzzyEngine(**broken(output_mfs=outputs))


def test_engine_refuses_an_unknown_output_off_centre() -> None:
    outputs = dict(paper_parts()["output_mfs"])
    outputs["UNK"] = Triangle(1 / 3, 0.55, 2 / 3)
    with pytest.raises(ValueError, match=r"output_mfs\['UNK'\] .* centred on risk 0.5"):
        FuzzyEngine(**broken(output_mfs=outputs))


def test_engine_refuses_outputs_out_of_risk_order() -> None:
    outputs = dict(paper_parts()["output_mfs"])
    outputs["PO"], outputs["MPO"] = outputs["MPO"], outputs["PO"]
    with pytest.raises(ValueError, match="output_mfs must follow labels in increasing risk: 'PO'"):
        FuzzyEngine(**broken(output_mfs=outputs))


def test_engine_refuses_a_label_active_forever_behind_the_surface() -> None:
    inputs = dict(paper_parts()["input_mfs"])
    inputs["OCC"] = RightShoulder(-1.0, 0.0)
    with pytest.raises(ValueError, match=r"input_mfs\['OCC'\] is positive up to \+inf"):
        FuzzyEngine(**broken(input_mfs=inputs))
    inputs["OCC"], inputs["UNK"] = Triangle(-1.0, 0.0, 1.5), Triangle(0.0, 1.5, 3.0)
    with pytest.raises(ValueError, match=r"do not cover .* \[3, inf\]$"):
        FuzzyEngine(**broken(input_mfs=inputs))


@dataclasses.dataclass(frozen=True)
class _LevelsOffAtHalf(MembershipFunction):
    """A user-defined ramp that stays at 0.5 behind the surface: unknown never becomes certain."""

    @property
    def breakpoints(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (0.0, 1.5), (0.0, 0.5)

    @property
    def support(self) -> tuple[float, float]:
        return 0.0, float("inf")


def test_engine_refuses_an_unknown_input_that_never_reaches_one() -> None:
    inputs = {**paper_parts()["input_mfs"], "UNK": _LevelsOffAtHalf()}
    with pytest.raises(ValueError, match=r"input_mfs\['UNK'\] \(the unknown label\) must reach 1"):
        FuzzyEngine(**broken(input_mfs=inputs))


def test_engine_is_frozen_and_comparable() -> None:
    e = FuzzyEngine.paper()
    with pytest.raises(dataclasses.FrozenInstanceError):
        e.and_op = "product"  # type: ignore[misc]
    assert e == FuzzyEngine.paper() and hash(e) == hash(FuzzyEngine.paper())
    assert e != FuzzyEngine.paper(and_op="product")
