"""A :class:`FuzzyEngine` as plain JSON-able data, and back: lossless and canonical.

>>> from fuzzyocc.engine import FuzzyEngine
>>> d = engine_to_dict(FuzzyEngine.paper())
>>> d["labels"], d["input_mfs"]["PO"]
(['EMP', 'MPE', 'PE', 'UNK', 'PO', 'MPO', 'OCC'], {'type': 'triangle', 'left': -3.0, 'peak': -2.0, 'right': -1.0})
>>> engine_from_dict(d) == FuzzyEngine.paper()
True

The dict holds every init field of the engine's dataclass, in field order::

    {"labels": [...], "unknown": "UNK", "input_mfs": {label: mf}, "output_mfs": {label: mf},
     "rules": {current: {new: conclusion}}, "and_op": "min", "or_op": "max", "normalize": false,
     "incidence_floor": 1.0, "no_return_neighbours": 0}

with an mf ``{"type": "triangle", "left", "peak", "right"}``, ``{"type": "trapezoid", "a", "b",
"c", "d"}``, ``{"type": "left_shoulder", "top_end", "zero_at"}`` or ``{"type": "right_shoulder",
"zero_at", "top_start"}`` (the parameters of :mod:`fuzzyocc.membership`'s dataclasses). Equal
engines give equal dicts (labels order throughout, numbers as floats, ``normalize`` resolved), so
the dict can be stored and compared. A field without a codec below is written as it is: a new
engine field holding a JSON value (with a default, so that dicts stored before it still load)
needs no change here. Lists read back as tuples, which keeps the engine hashable.

Every error is a ``ValueError`` whose message starts with the path of the bad field, e.g.
``engine.input_mfs.PO.peak must be a finite number, got nan``; the engine's own checks are
reported under ``engine.``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Mapping
from typing import Any

from fuzzyocc.engine import FuzzyEngine
from fuzzyocc.membership import LeftShoulder, MembershipFunction, RightShoulder, Trapezoid, Triangle

__all__ = ["MF_TYPES", "engine_from_dict", "engine_to_dict", "mf_from_dict", "mf_to_dict"]

#: The membership functions that have a data form, by their ``"type"``.
MF_TYPES: Mapping[str, type[MembershipFunction]] = {
    "triangle": Triangle,
    "trapezoid": Trapezoid,
    "left_shoulder": LeftShoulder,
    "right_shoulder": RightShoulder,
}
_TYPE_NAMES = {cls: name for name, cls in MF_TYPES.items()}
_ROOT = "engine"


# ---------------------------------------------------------------- membership functions
def _params(cls: type[MembershipFunction]) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def mf_to_dict(mf: MembershipFunction, path: str = "mf") -> dict[str, Any]:
    """``{"type": ..., <parameter>: float, ...}``; ``ValueError`` for a function without a data form."""
    name = _TYPE_NAMES.get(type(mf))  # exact type: a subclass may evaluate differently
    if name is None:
        raise ValueError(f"{path} is a {type(mf).__name__}, which has no data form (one of {list(MF_TYPES)})")
    # + 0.0: -0.0 and 0.0 are the same parameter, so they get one spelling
    return {"type": name, **{p: float(getattr(mf, p)) + 0.0 for p in _params(type(mf))}}


def mf_from_dict(d: object, path: str = "mf") -> MembershipFunction:
    """The membership function ``d`` describes; ``ValueError`` naming ``path`` and the bad parameter."""
    if not isinstance(d, Mapping):
        raise ValueError(f"{path} must be an object with a \"type\" and its parameters, got {_show(d)}")
    kind = d.get("type")
    cls = MF_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise ValueError(f"{path}.type must be one of {list(MF_TYPES)}, got {_show(kind)}")
    params = _params(cls)
    for key in d:
        if key != "type" and key not in params:
            raise ValueError(f"{path}.{key} is not a parameter of a {kind} (its parameters: {params})")
    values = {p: _finite(d[p] if p in d else _MISSING, f"{path}.{p}") for p in params}
    try:
        return cls(**values)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


# ---------------------------------------------------------------- field codecs
def _encode_mfs(mfs: tuple[tuple[str, MembershipFunction], ...], path: str) -> dict[str, Any]:
    return {label: mf_to_dict(mf, f"{path}.{label}") for label, mf in mfs}


def _encode_rules(rules: tuple[tuple[str, ...], ...], labels: tuple[str, ...]) -> dict[str, dict[str, str]]:
    return {current: dict(zip(labels, row)) for current, row in zip(labels, rules)}


def _decode_labels(value: object, path: str) -> tuple[str, ...]:
    if not isinstance(value, list):
        raise ValueError(f"{path} must be a list of label names, got {_show(value)}")
    for k, label in enumerate(value):
        if not isinstance(label, str):
            raise ValueError(f"{path}[{k}] must be a label name (a string), got {_show(label)}")
    return tuple(value)


def _decode_mfs(value: object, path: str) -> dict[str, MembershipFunction]:
    if not isinstance(value, Mapping):
        raise ValueError(f"{path} must be an object label -> membership function, got {_show(value)}")
    return {label: mf_from_dict(mf, f"{path}.{label}") for label, mf in value.items()}


def _decode_rules(value: object, path: str) -> dict[str, dict[str, str]]:
    if not isinstance(value, Mapping):
        raise ValueError(f"{path} must be an object current label -> {{new label -> conclusion}}, got {_show(value)}")
    rules: dict[str, dict[str, str]] = {}
    for current, row in value.items():
        if not isinstance(row, Mapping):
            raise ValueError(f"{path}.{current} must be an object new label -> conclusion, got {_show(row)}")
        for new, conclusion in row.items():
            if not isinstance(conclusion, str):
                raise ValueError(f"{path}.{current}.{new} must be a label name (a string), got {_show(conclusion)}")
        rules[current] = dict(row)
    return rules


def _typed(*types: type) -> Callable[[object, str], object]:
    names = " or ".join("null" if t is type(None) else {str: "a string", bool: "true or false"}[t] for t in types)

    def decode(value: object, path: str) -> object:
        if not isinstance(value, types):
            raise ValueError(f"{path} must be {names}, got {_show(value)}")
        return value

    return decode


#: Decoders of the fields that need more than :func:`_from_json`, by field name.
_DECODERS: Mapping[str, Callable[[object, str], object]] = {
    "labels": _decode_labels,
    "unknown": _typed(str),
    "input_mfs": _decode_mfs,
    "output_mfs": _decode_mfs,
    "rules": _decode_rules,
    "and_op": _typed(str),
    "or_op": _typed(str),
    "normalize": _typed(bool, type(None)),
}


# ---------------------------------------------------------------- the engine
def engine_to_dict(engine: FuzzyEngine) -> dict[str, Any]:
    """Every init field of ``engine``'s dataclass as JSON-able data (see the module docstring)."""
    out: dict[str, Any] = {}
    for f in _init_fields(type(engine)):
        value = getattr(engine, f.name)
        path = f"{_ROOT}.{f.name}"
        if f.name in ("input_mfs", "output_mfs"):
            out[f.name] = _encode_mfs(value, path)
        elif f.name == "rules":
            out[f.name] = _encode_rules(value, engine.labels)
        else:
            out[f.name] = _to_json(value, path)
    return out


def engine_from_dict(d: Mapping[str, Any], *, cls: type[FuzzyEngine] = FuzzyEngine, root: str = _ROOT) -> FuzzyEngine:
    """The engine ``d`` describes (the inverse of :func:`engine_to_dict`).

    A field with a default may be left out. ``cls``: a subclass of :class:`FuzzyEngine` to
    build instead (its extra fields are read like any other). ``root``: the path the messages
    name ``d`` by (``engine.definition`` where the definition sits inside another object).

    Raises
    ------
    ValueError
        Naming the path of the bad field (``engine.rules.PO.EMP ...``), or the engine's own
        check prefixed with ``engine.`` (coverage, rule table, output order ...).
    """
    if not isinstance(d, Mapping):
        raise ValueError(f"{root} must be an object of engine fields, got {_show(d)}")
    fields = {f.name: f for f in _init_fields(cls)}
    for key in d:
        if key not in fields:
            raise ValueError(f"{root}.{key} is not a field of an engine (the fields: {list(fields)})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        path = f"{root}.{name}"
        if name not in d:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ValueError(f"{path} is missing")
            continue
        kwargs[name] = _DECODERS.get(name, _from_json)(d[name], path)
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(_under_root(str(exc), fields, root)) from None


def _init_fields(cls: type) -> list[dataclasses.Field[Any]]:
    return [f for f in dataclasses.fields(cls) if f.init]


def _under_root(message: str, fields: Mapping[str, object], root: str) -> str:
    # the engine's messages start with the field they are about ("rules['PO']['EMP'] concludes ...")
    head = message.split(" ", 1)[0].split("[", 1)[0]
    return f"{root}.{message}" if head in fields else f"{root}: {message}"


# ---------------------------------------------------------------- plain values
_MISSING = object()


def _finite(value: object, path: str) -> float:
    if value is _MISSING:
        raise ValueError(f"{path} is missing")
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{path} must be a finite number, got {_show(value)}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond the float range
        number = math.inf
    if not math.isfinite(number):
        raise ValueError(f"{path} must be a finite number, got {_show(value)}")
    return number


def _to_json(value: object, path: str) -> object:
    """A field without a codec, as JSON: scalars as they are, tuples as lists."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return _finite(value, path) + 0.0
    if isinstance(value, (tuple, list)):
        return [_to_json(v, f"{path}[{k}]") for k, v in enumerate(value)]
    if isinstance(value, Mapping) and all(isinstance(k, str) for k in value):
        return {k: _to_json(v, f"{path}.{k}") for k, v in value.items()}
    raise ValueError(f"{path} holds a {type(value).__name__}, which has no JSON form")


def _from_json(value: object, path: str) -> object:
    """A field without a codec, from JSON: lists as tuples (engines are hashable), numbers finite."""
    if value is None or isinstance(value, (bool, str, int)):
        return value
    if isinstance(value, float):
        return _finite(value, path)
    if isinstance(value, list):
        return tuple(_from_json(v, f"{path}[{k}]") for k, v in enumerate(value))
    if isinstance(value, Mapping):
        return {k: _from_json(v, f"{path}.{k}") for k, v in value.items()}
    raise ValueError(f"{path} must be a JSON value, got {_show(value)}")


def _show(value: object, limit: int = 60) -> str:
    """``repr`` cut short: the bad value may be a huge list."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({type(value).__name__})"
