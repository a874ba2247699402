"""Engines as data (fuzzyocc.engine_spec) and the named presets (fuzzyocc.presets)."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fuzzyocc import presets
from fuzzyocc.engine import PAPER_INPUT_PEAKS, PAPER_LABELS, PAPER_RULES, FuzzyEngine, even_output_mfs
from fuzzyocc.engine_spec import engine_from_dict, engine_to_dict
from fuzzyocc.membership import LeftShoulder, MembershipFunction, RightShoulder, Trapezoid, Triangle, ladder

OPERATORS = [("min", "max"), ("product", "max"), ("min", "probsum"), ("product", "probsum")]
NINE = ("EMP", "MPE", "PE", "SE", "UNK", "SO", "PO", "MPO", "OCC")


def nine_label_engine() -> FuzzyEngine:
    """9 labels (the paper's "larger number of members"), a rule stepping one label toward the evidence."""
    distance_order = ("EMP", "MPE", "PE", "SE", "SO", "PO", "MPO", "OCC", "UNK")
    peaks = (-7.0, -6.0, -5.0, -4.0, -3.0, -2.0, -1.0, 0.0, 1.5)
    rules = [[cur if new == "UNK" else NINE[NINE.index(cur) + int(np.sign(NINE.index(new) - NINE.index(cur)))]
              for new in NINE] for cur in NINE]
    return FuzzyEngine(NINE, "UNK", dict(zip(distance_order, ladder(peaks))), even_output_mfs(NINE), rules,
                       and_op="product", or_op="probsum")


def paper_dict() -> dict[str, Any]:
    return engine_to_dict(FuzzyEngine.paper())


# ---------------------------------------------------------------- round trips
@pytest.mark.parametrize("make", [FuzzyEngine.paper, nine_label_engine,
                                  *[lambda a=a, o=o: FuzzyEngine.paper(and_op=a, or_op=o) for a, o in OPERATORS]])
def test_an_engine_survives_the_dict_and_json_text(make: Any) -> None:
    engine = make()
    d = engine_to_dict(engine)
    assert engine_from_dict(d) == engine
    text = json.dumps(d, allow_nan=False)  # strict JSON: what is stored and served
    assert engine_from_dict(json.loads(text)) == engine
    assert engine_to_dict(engine_from_dict(json.loads(text))) == d


def test_the_dict_has_the_documented_shape() -> None:
    d = paper_dict()
    assert list(d) == ["labels", "unknown", "input_mfs", "output_mfs", "rules", "and_op", "or_op", "normalize",
                       "incidence_floor", "no_return_neighbours"]
    assert d["labels"] == list(PAPER_LABELS) and d["unknown"] == "UNK"
    assert d["input_mfs"]["EMP"] == {"type": "left_shoulder", "top_end": -5.0, "zero_at": -4.0}
    assert d["input_mfs"]["PO"] == {"type": "triangle", "left": -3.0, "peak": -2.0, "right": -1.0}
    assert d["input_mfs"]["UNK"] == {"type": "right_shoulder", "zero_at": 0.0, "top_start": 1.5}
    assert d["rules"]["PO"]["EMP"] == PAPER_RULES["PO"]["EMP"]
    assert (d["and_op"], d["or_op"], d["normalize"]) == ("min", "max", False)


def test_equal_engines_give_the_same_dict_and_the_same_text() -> None:
    """Canonical: how an engine was spelled (ints, row order, nested lists, -0.0) does not show."""
    inputs = dict(zip(("EMP", "MPE", "PE", "PO", "MPO", "OCC", "UNK"), ladder(PAPER_INPUT_PEAKS)))
    inputs["OCC"] = Triangle(-1, 0, 1.5)
    inputs["UNK"] = RightShoulder(-0.0, 1.5)
    shuffled = dict(reversed(list(inputs.items())))
    as_rows = [[PAPER_RULES[cur][new] for new in PAPER_LABELS] for cur in PAPER_LABELS]
    spelled = FuzzyEngine(PAPER_LABELS, "UNK", shuffled, even_output_mfs(PAPER_LABELS), as_rows, normalize=None)
    assert spelled == FuzzyEngine.paper()
    assert json.dumps(engine_to_dict(spelled)) == json.dumps(paper_dict())


def test_every_membership_type_has_a_data_form() -> None:
    outputs = dict(even_output_mfs(PAPER_LABELS))
    outputs["UNK"] = Trapezoid(1 / 3, 0.45, 0.55, 2 / 3)
    engine = FuzzyEngine(PAPER_LABELS, "UNK", paper_parts_inputs(), outputs, PAPER_RULES)
    d = engine_to_dict(engine)
    assert d["output_mfs"]["UNK"] == {"type": "trapezoid", "a": 1 / 3, "b": 0.45, "c": 0.55, "d": 2 / 3}
    assert engine_from_dict(d) == engine


def paper_parts_inputs() -> dict[str, MembershipFunction]:
    return dict(zip(("EMP", "MPE", "PE", "PO", "MPO", "OCC", "UNK"), ladder(PAPER_INPUT_PEAKS)))


def test_fields_with_defaults_may_be_left_out() -> None:
    d = paper_dict()
    for name in ("and_op", "or_op", "normalize"):
        del d[name]
    assert engine_from_dict(d) == FuzzyEngine.paper()
    assert engine_from_dict({**d, "and_op": "product"}) == FuzzyEngine.paper(and_op="product")  # normalize: auto


# ---------------------------------------------------------------- a field added to the engine later
@dataclasses.dataclass(frozen=True)
class _EngineWithMore(FuzzyEngine):
    """FuzzyEngine as it may grow: new plain fields with defaults."""

    decay: float = 0.0
    tags: tuple[str, ...] = ()


def test_a_new_plain_field_round_trips_and_old_dicts_still_load() -> None:
    paper = FuzzyEngine.paper()
    grown = _EngineWithMore(**{f.name: getattr(paper, f.name) for f in dataclasses.fields(FuzzyEngine) if f.init},
                            decay=0.25, tags=("tuned", "hall"))
    d = engine_to_dict(grown)
    assert d["decay"] == 0.25 and d["tags"] == ["tuned", "hall"]
    back = engine_from_dict(json.loads(json.dumps(d)), cls=_EngineWithMore)
    assert back == grown and hash(back) == hash(grown)  # lists read back as tuples: still hashable
    old = engine_from_dict(paper_dict(), cls=_EngineWithMore)  # stored before the field existed
    assert (old.decay, old.tags) == (0.0, ()) and old.rules == paper.rules
    with pytest.raises(ValueError, match=r"^engine\.decay is not a field of an engine"):
        engine_from_dict(d)  # an engine without the field refuses it rather than dropping it


# ---------------------------------------------------------------- errors name the field
def _set(d: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    out = copy.deepcopy(d)
    *parents, last = path.split(".")
    node = out
    for key in parents:
        node = node[key]
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value
    return out


_DELETE = object()


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("input_mfs.PO.peak", math.nan, r"^engine\.input_mfs\.PO\.peak must be a finite number, got nan$"),
        ("input_mfs.PO.peak", math.inf, r"^engine\.input_mfs\.PO\.peak must be a finite number"),
        ("input_mfs.PO.peak", "-2", r"^engine\.input_mfs\.PO\.peak must be a finite number, got '-2'"),
        ("input_mfs.PO.peak", True, r"^engine\.input_mfs\.PO\.peak must be a finite number"),
        ("input_mfs.PO.peak", 10**400, r"^engine\.input_mfs\.PO\.peak must be a finite number"),
        ("input_mfs.PO.peak", _DELETE, r"^engine\.input_mfs\.PO\.peak is missing$"),
        ("input_mfs.PO.top", 1.0, r"^engine\.input_mfs\.PO\.top is not a parameter of a triangle"),
        ("input_mfs.PO.type", "bell", r"^engine\.input_mfs\.PO\.type must be one of \['triangle'"),
        ("input_mfs.PO.peak", -4.0, r"^engine\.input_mfs\.PO: Triangle needs left < peak"),
        ("input_mfs.PO", [-3, -2, -1], r"^engine\.input_mfs\.PO must be an object"),
        ("input_mfs", [], r"^engine\.input_mfs must be an object label -> membership function"),
        ("output_mfs.OCC", {"type": "left_shoulder", "top_end": 0.9, "zero_at": 1.0}, r"^engine\.output_mfs"),
        ("labels", "EMP MPE", r"^engine\.labels must be a list of label names"),
        ("labels", ["EMP", 7], r"^engine\.labels\[1\] must be a label name"),
        ("labels", ["EMP", "EMP"], r"^engine\.labels must be distinct"),
        ("unknown", "VOID", r"^engine\.unknown label 'VOID' is not one of labels"),
        ("unknown", None, r"^engine\.unknown must be a string, got None"),
        ("rules.PO.EMP", "FOO", r"^engine\.rules\['PO'\]\['EMP'\] concludes 'FOO', which is not one of"),
        ("rules.PO.EMP", 3, r"^engine\.rules\.PO\.EMP must be a label name"),
        ("rules.FOO", dict(PAPER_RULES["PO"]), r"^engine\.rules \(rows\) must name exactly the labels .* \['FOO'\]"),
        ("rules.PO", ["EMP"] * 7, r"^engine\.rules\.PO must be an object"),
        ("rules.PO.UNK", "EMP", r"^engine\.rules\['PO'\]\['UNK'\] concludes 'EMP'; the unknown column"),
        ("rules", _DELETE, r"^engine\.rules is missing$"),
        ("and_op", "max", r"^engine\.and_op must be one of \['min', 'product'\]"),
        ("or_op", 1, r"^engine\.or_op must be a string"),
        ("normalize", "yes", r"^engine\.normalize must be true or false or null"),
        ("colour", "red", r"^engine\.colour is not a field of an engine"),
    ],
)
def test_a_bad_definition_is_refused_naming_the_field(path: str, value: Any, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        engine_from_dict(_set(paper_dict(), path, value))


def test_input_functions_that_leave_a_gap_are_refused_with_the_gap() -> None:
    d = _set(paper_dict(), "input_mfs.MPE", {"type": "triangle", "left": -5.0, "peak": -4.5, "right": -4.0})
    d = _set(d, "input_mfs.PE", {"type": "triangle", "left": -3.0, "peak": -2.5, "right": -2.0})
    with pytest.raises(ValueError, match=r"^engine\.input_mfs \(distance axis, sigmas\) do not cover .* \[-4, -3\]$"):
        engine_from_dict(d)


def test_an_engine_that_is_not_an_object_is_refused() -> None:
    with pytest.raises(ValueError, match=r"^engine must be an object of engine fields, got \["):
        engine_from_dict([1, 2])  # type: ignore[arg-type]


def test_a_membership_function_without_a_data_form_is_named() -> None:
    @dataclasses.dataclass(frozen=True)
    class Step(MembershipFunction):
        @property
        def breakpoints(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
            return (0.0, 1e-9), (0.0, 1.0)

        @property
        def support(self) -> tuple[float, float]:
            return 0.0, math.inf

    engine = FuzzyEngine(PAPER_LABELS, "UNK", {**paper_parts_inputs(), "UNK": Step()}, even_output_mfs(PAPER_LABELS),
                         PAPER_RULES)
    with pytest.raises(ValueError, match=r"^engine\.input_mfs\.UNK is a Step, which has no data form"):
        engine_to_dict(engine)


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix] if prefix else []
    children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else []
    for key, child in children:
        out += _paths(child, (*prefix, key))
    return out


PAPER_PATHS = _paths(paper_dict())


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(where=st.sampled_from(PAPER_PATHS), value=JSON)
def test_any_json_anywhere_gives_an_engine_or_a_value_error(where: tuple[Any, ...], value: Any) -> None:
    """A client's definition can hold anything: it is refused with a ValueError, never another exception."""
    d = paper_dict()
    node = d
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    try:
        engine_from_dict(d)
    except ValueError as exc:
        assert str(exc).startswith("engine")


@settings(max_examples=100, deadline=None)
@given(value=JSON)
def test_any_json_as_the_whole_definition_gives_a_value_error(value: Any) -> None:
    with pytest.raises(ValueError, match="^engine"):
        engine_from_dict(value)


# ---------------------------------------------------------------- presets
@pytest.mark.parametrize("name", sorted(presets.PRESETS))
def test_every_preset_builds_round_trips_and_knows_its_name(name: str) -> None:
    engine = presets.preset(name)
    assert isinstance(engine, FuzzyEngine)
    assert presets.preset(name) is engine  # built once
    assert presets.preset_name_of(engine_from_dict(engine_to_dict(engine))) == name


def test_the_default_preset_is_a_preset_and_paper_is_the_papers_engine() -> None:
    assert presets.DEFAULT_PRESET in presets.PRESETS
    assert presets.preset("paper") == FuzzyEngine.paper()


def test_an_engine_equal_to_no_preset_has_no_name() -> None:
    assert presets.preset_name_of(FuzzyEngine.paper(and_op="product")) is None
    assert presets.preset_name_of(nine_label_engine()) is None


def test_an_unknown_preset_is_refused_listing_the_names() -> None:
    with pytest.raises(ValueError, match=r"no engine preset named 'papr'; the presets are \[.*'paper'.*\]"):
        presets.preset("papr")


def test_left_shoulder_parameters_are_the_dataclass_names() -> None:
    d = paper_dict()
    for mf in (*d["input_mfs"].values(), *d["output_mfs"].values()):
        cls = {"triangle": Triangle, "trapezoid": Trapezoid, "left_shoulder": LeftShoulder,
               "right_shoulder": RightShoulder}[mf["type"]]
        assert list(mf)[1:] == [f.name for f in dataclasses.fields(cls)]
