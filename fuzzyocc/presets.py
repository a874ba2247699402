"""Named fuzzy engines: what a map may ask for by name instead of a full definition.

To add a preset, register its factory in ``PRESETS``; to change what a map gets when it names
none, set ``DEFAULT_PRESET``. A map stores its engine's full definition, so neither change
alters an existing map.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from types import MappingProxyType

from fuzzyocc.engine import FuzzyEngine
from fuzzyocc.evidence import evidence_engine

__all__ = ["DEFAULT_PRESET", "PRESETS", "preset", "preset_name_of"]

#: Factories of the named engines.
PRESETS: Mapping[str, Callable[[], FuzzyEngine]] = MappingProxyType({
    "paper": FuzzyEngine.paper,  # Payeur's Table 1, min/max (FuzzyEngine.paper)
    "evidence": evidence_engine,  # 11 evidence levels, tuned on recorded logs (fuzzyocc.evidence)
})

#: The preset of a map that names none (and of ``FuzzyMap`` without an engine).
DEFAULT_PRESET: str = "evidence"


@functools.cache
def preset(name: str) -> FuzzyEngine:
    """The engine of preset ``name`` (built once); ``ValueError`` listing the known names."""
    factory = PRESETS.get(name)
    if factory is None:
        raise ValueError(f"no engine preset named {name!r}; the presets are {sorted(PRESETS)}")
    return factory()


def preset_name_of(engine: FuzzyEngine) -> str | None:
    """The name of the first preset equal to ``engine``, or None."""
    return next((name for name in PRESETS if preset(name) == engine), None)
