"""A fuzzy map's engine as the service takes it, stores it and shows it.

Taken: a preset name (``fuzzyocc.presets``), a full definition (``fuzzyocc.engine_spec``'s
dict), or the object ``GET /maps/{name}`` shows, ``{"preset", "definition"}`` (either, or both
when they agree), bounded before anything is built. What a definition costs the service is its
defuzzification: with at most two output functions overlapping anywhere, the engine tabulates
the risk (one table of 65536 entries, 1 MiB, per overlapping pair: at most ``MAX_LABELS`` MiB
and ~0.1 s once per engine) and a cell's risk is a few lookups; with three, every cell's risk
is computed on 1000 samples, ~150 times slower, for every cell a scan changes. So a
definition has at most ``MAX_LABELS`` labels and pairwise-overlapping outputs.

Stored and shown as ``{"preset", "definition"}`` (``EngineChoice.as_object``): stored, the
preset asked for; shown, the preset the engine equals now. A restart rebuilds the engine from
the definition, so a preset changed later does not change the map.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from fuzzyocc import presets
from fuzzyocc.engine import RISK_SAMPLES, FuzzyEngine
from fuzzyocc.engine_spec import engine_from_dict, engine_to_dict

#: Most labels of an engine definition.
MAX_LABELS = 16
#: Longest label name (and any other string) in an engine definition.
MAX_NAME_CHARS = 32
#: Most JSON values in an engine definition (16 labels take about 500).
MAX_VALUES = 2048
#: The engine of a map stored before maps chose theirs: all were made with the paper's engine
#: (not ``DEFAULT_PRESET``, which may move on).
UNRECORDED = "paper"
#: The keys of the engine object (``EngineInfo``): what ``GET /maps/{name}`` shows.
OBJECT_KEYS = ("preset", "definition")


@dataclass(frozen=True)
class EngineChoice:
    """An engine and its preset name (None: none): as a new map asked for it, or as its map shows it."""

    engine: FuzzyEngine
    preset: str | None

    @functools.cached_property
    def definition(self) -> dict[str, Any]:
        """The engine in full (``engine_to_dict``)."""
        return engine_to_dict(self.engine)

    def as_object(self) -> dict[str, Any]:
        """``{"preset", "definition"}``: what the map's meta stores and ``GET /maps/{name}`` shows."""
        return {"preset": self.preset, "definition": self.definition}


def parse(value: object) -> EngineChoice | None:
    """The ``engine`` of a map request: None, a preset name, a definition or the object GET shows.

    ``ValueError`` naming the field. An ``EngineChoice`` is taken as it is (a map's engine shown
    again: the limits apply to new maps, a stored map must show).
    """
    if value is None or isinstance(value, EngineChoice):
        return value
    if isinstance(value, str):
        return EngineChoice(_preset(value, "engine"), value)
    if isinstance(value, Mapping):
        if any(key in value for key in OBJECT_KEYS):
            return _parse_object(value)
        return EngineChoice(_definition(value, "engine"), None)
    raise ValueError(f"engine must be a preset name (one of {sorted(presets.PRESETS)}) or an engine definition "
                     f"(an object: the definition, or {{\"preset\", \"definition\"}} as GET /maps/{{name}} "
                     f"shows it), got {type(value).__name__}")


def default() -> EngineChoice:
    """The engine of a fuzzy map that names none: ``DEFAULT_PRESET``, read when the map is made."""
    name = presets.DEFAULT_PRESET
    return EngineChoice(presets.preset(name), name)


def shown(engine: FuzzyEngine) -> EngineChoice:
    """A map's engine as ``GET /maps/{name}`` shows it: under the preset it equals now, if any."""
    return EngineChoice(engine, presets.preset_name_of(engine))


def from_meta(meta: Mapping[str, Any]) -> FuzzyEngine:
    """The engine of a stored fuzzy map (no limits: they apply to new maps, a stored map must load)."""
    stored = meta.get("engine")
    if stored is None:
        return presets.preset(UNRECORDED)
    return engine_from_dict(stored.get("definition") if isinstance(stored, Mapping) else stored)


def _parse_object(value: Mapping[str, Any]) -> EngineChoice:
    """``{"preset", "definition"}``: either one, or both when the definition is the preset's engine."""
    for key in value:
        if key not in OBJECT_KEYS:
            raise ValueError(f"engine.{str(key)[:MAX_NAME_CHARS]} is not a field of the engine object "
                             f"{{\"preset\", \"definition\"}}; an engine's fields go under engine.definition")
    name, definition = value.get("preset"), value.get("definition")
    if name is not None and not isinstance(name, str):
        raise ValueError(f"engine.preset must be a preset name (one of {sorted(presets.PRESETS)}) or null, got "
                         f"{type(name).__name__}")
    if name is None and definition is None:
        raise ValueError("engine needs a preset or a definition; leave engine out for the default preset")
    if definition is None:
        assert name is not None
        return EngineChoice(_preset(name, "engine.preset"), name)
    engine = _definition(definition, "engine.definition")
    if name is not None and _preset(name, "engine.preset") != engine:
        equal = presets.preset_name_of(engine)
        raise ValueError(
            f"engine.preset is {name!r} but engine.definition is another engine (it equals "
            f"{'the preset ' + repr(equal) if equal else 'no preset'}); send the preset alone, the definition "
            "alone (preset null), or both as GET /maps/{name} shows them"
        )
    return EngineChoice(engine, name)


def _preset(name: str, path: str) -> FuzzyEngine:
    if len(name) > MAX_NAME_CHARS:  # not quoted back in full
        raise ValueError(f"{path} is a {len(name)}-character string; a preset name is one of "
                         f"{sorted(presets.PRESETS)}")
    try:
        return presets.preset(name)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _definition(definition: object, path: str) -> FuzzyEngine:
    if isinstance(definition, Mapping):
        _check_size(definition, path)
    engine = engine_from_dict(definition, root=path)  # type: ignore[arg-type]  # it names a non-object
    _check_pairwise_outputs(engine, path)
    return engine


def _check_size(definition: Mapping[str, Any], root: str) -> None:
    labels = definition.get("labels")
    if isinstance(labels, list):
        if len(labels) > MAX_LABELS:
            raise ValueError(f"{root}.labels has {len(labels)} labels; at most {MAX_LABELS}")
        for k, label in enumerate(labels):
            if isinstance(label, str) and not label:
                raise ValueError(f"{root}.labels[{k}] is empty; a label needs a name")
    # every value, iteratively (no recursion on hostile nesting): bounds what the engine's checks
    # walk and what their messages may quote
    todo: list[tuple[object, str]] = [(definition, root)]
    seen = 0
    while todo:
        value, path = todo.pop()
        seen += 1
        if seen > MAX_VALUES:
            raise ValueError(f"{root} holds more than {MAX_VALUES} values; a definition of {MAX_LABELS} labels "
                             "needs about 500")
        if isinstance(value, str) and len(value) > MAX_NAME_CHARS:
            raise ValueError(f"{path} is {len(value)} characters long; at most {MAX_NAME_CHARS}")
        if isinstance(value, Mapping):
            for key, item in value.items():
                if len(key) > MAX_NAME_CHARS:
                    raise ValueError(f"{path} has a key of {len(key)} characters; at most {MAX_NAME_CHARS}")
                todo.append((item, f"{path}.{key}"))
        elif isinstance(value, list):
            todo.extend((item, f"{path}[{k}]") for k, item in enumerate(value))


def _check_pairwise_outputs(engine: FuzzyEngine, root: str) -> None:
    x = (np.arange(RISK_SAMPLES) + 0.5) / RISK_SAMPLES  # the engine's risk samples
    positive = np.stack([mf(x) for _, mf in engine.output_mfs]) > 0.0
    counts = positive.sum(axis=0)
    worst = int(counts.argmax())
    if counts[worst] > 2:
        names = [engine.labels[k] for k in np.flatnonzero(positive[:, worst])]
        raise ValueError(
            f"{root}.output_mfs {names} are all positive at risk {x[worst]:.4g}; the service needs at most two "
            "output functions positive at any risk (it tabulates the risk per overlapping pair)"
        )
