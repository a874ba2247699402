"""A fuzzy map's engine as the service takes it, stores it and shows it.

Taken: a preset name (``fuzzyocc.presets``) or a full definition (``fuzzyocc.engine_spec``'s
dict), bounded before anything is built. What a definition costs the service is its
defuzzification: with at most two output functions overlapping anywhere, the engine tabulates
the risk (one table of 65536 entries, 1 MiB, per overlapping pair: at most ``MAX_LABELS`` MiB
and ~0.1 s once per engine) and a cell's risk is a few lookups; with three, every cell's risk
is computed on 1000 samples, ~150 times slower, for every cell a scan changes. So a
definition has at most ``MAX_LABELS`` labels and pairwise-overlapping outputs.

Stored: ``{"preset": name or null, "definition": {...}}`` in the map's meta; a restart
rebuilds the engine from the definition, so a preset changed later does not change the map.
"""

from __future__ import annotations

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


@dataclass(frozen=True)
class EngineChoice:
    """The engine a new map asked for: the engine, and the preset name it was asked by (None: a definition)."""

    engine: FuzzyEngine
    preset: str | None


def parse(value: object) -> EngineChoice | None:
    """The ``engine`` of a map request: None, a preset name or a definition; ``ValueError`` naming the field."""
    if value is None:
        return None
    if isinstance(value, str):
        if len(value) > MAX_NAME_CHARS:  # not quoted back in full
            raise ValueError(f"engine is a {len(value)}-character string; a preset name is one of "
                             f"{sorted(presets.PRESETS)}")
        return EngineChoice(presets.preset(value), value)
    if isinstance(value, Mapping):
        _check_size(value)
        engine = engine_from_dict(value)
        _check_pairwise_outputs(engine)
        return EngineChoice(engine, None)
    raise ValueError(f"engine must be a preset name (one of {sorted(presets.PRESETS)}) or an engine definition "
                     f"(an object), got {type(value).__name__}")


def default() -> EngineChoice:
    """The engine of a fuzzy map that names none: ``DEFAULT_PRESET``, read when the map is made."""
    name = presets.DEFAULT_PRESET
    return EngineChoice(presets.preset(name), name)


def to_meta(choice: EngineChoice) -> dict[str, Any]:
    """What the map's stored meta keeps under ``"engine"``."""
    return {"preset": choice.preset, "definition": engine_to_dict(choice.engine)}


def from_meta(meta: Mapping[str, Any]) -> FuzzyEngine:
    """The engine of a stored fuzzy map (no limits: they apply to new maps, a stored map must load)."""
    stored = meta.get("engine")
    if stored is None:
        return presets.preset(UNRECORDED)
    return engine_from_dict(stored.get("definition") if isinstance(stored, Mapping) else stored)


def describe(engine: FuzzyEngine) -> dict[str, Any]:
    """``{"preset": the preset the engine equals or None, "definition": its dict}`` (``MapInfo.engine``)."""
    return {"preset": presets.preset_name_of(engine), "definition": engine_to_dict(engine)}


def _check_size(definition: Mapping[str, Any]) -> None:
    labels = definition.get("labels")
    if isinstance(labels, list):
        if len(labels) > MAX_LABELS:
            raise ValueError(f"engine.labels has {len(labels)} labels; at most {MAX_LABELS}")
        for k, label in enumerate(labels):
            if isinstance(label, str) and not label:
                raise ValueError(f"engine.labels[{k}] is empty; a label needs a name")
    # every value, iteratively (no recursion on hostile nesting): bounds what the engine's checks
    # walk and what their messages may quote
    todo: list[tuple[object, str]] = [(definition, "engine")]
    seen = 0
    while todo:
        value, path = todo.pop()
        seen += 1
        if seen > MAX_VALUES:
            raise ValueError(f"engine holds more than {MAX_VALUES} values; a definition of {MAX_LABELS} labels "
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


def _check_pairwise_outputs(engine: FuzzyEngine) -> None:
    x = (np.arange(RISK_SAMPLES) + 0.5) / RISK_SAMPLES  # the engine's risk samples
    positive = np.stack([mf(x) for _, mf in engine.output_mfs]) > 0.0
    counts = positive.sum(axis=0)
    worst = int(counts.argmax())
    if counts[worst] > 2:
        names = [engine.labels[k] for k in np.flatnonzero(positive[:, worst])]
        raise ValueError(
            f"engine.output_mfs {names} are all positive at risk {x[worst]:.4g}; the service needs at most two "
            "output functions positive at any risk (it tabulates the risk per overlapping pair)"
        )
