"""The maps the service holds in memory, their write path, and their stored form.

A held map is a ``MapEntry`` (``entry``: its writers' ``Line`` from ``line``, its ``MapObserver``
hook); reads and plans get its grid at one version as a ``GridSnapshot`` (``snapshot``). ``MapRegistry``
(``registry``) says which maps exist; ``WritePath`` (``writepath``) takes a batch through parsing
(``ingest``, ``ingest_process``), commit (the log record: ``logcodec``), fusion and snapshots;
``stored`` rebuilds a map from its rows (``restore``). ``PlanGrids`` (``shared_grids``) publishes map
versions as files for the planner workers. Nothing here knows of HTTP, readers or planners.

The names are imported at their first use: a planner worker imports ``app.maps.shared_grids`` alone, and
should not pay for the write path's imports (storage, metrics, PIL).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.maps.entry import (
        UNLIMITED_CELLS,
        MapEntry,
        MapObserver,
        OccupancyMap,
        copy_limit,
        history_of,
        in_use,
        is_current,
        map_info,
        now,
        stored_info,
    )
    from app.maps.line import Line, Turns, shielded
    from app.maps.registry import MapRegistry
    from app.maps.shared_grids import FieldCache, GridRef, Lease, PlanGrids
    from app.maps.snapshot import GridSnapshot, GridStamp
    from app.maps.stored import Replayed, build_map, replay, restore
    from app.maps.writepath import WritePath

__all__ = [
    "FieldCache",
    "GridRef",
    "GridSnapshot",
    "GridStamp",
    "Lease",
    "Line",
    "MapEntry",
    "MapObserver",
    "MapRegistry",
    "OccupancyMap",
    "PlanGrids",
    "Replayed",
    "Turns",
    "UNLIMITED_CELLS",
    "WritePath",
    "build_map",
    "copy_limit",
    "history_of",
    "in_use",
    "is_current",
    "map_info",
    "now",
    "replay",
    "restore",
    "shielded",
    "stored_info",
]

_LAZY = {
    **dict.fromkeys(["UNLIMITED_CELLS", "MapEntry", "MapObserver", "OccupancyMap", "copy_limit", "history_of", "in_use",
                     "is_current", "map_info", "now", "stored_info"], "app.maps.entry"),
    **dict.fromkeys(["Line", "Turns", "shielded"], "app.maps.line"),
    "MapRegistry": "app.maps.registry",
    **dict.fromkeys(["FieldCache", "GridRef", "Lease", "PlanGrids"], "app.maps.shared_grids"),
    **dict.fromkeys(["GridSnapshot", "GridStamp"], "app.maps.snapshot"),
    **dict.fromkeys(["Replayed", "build_map", "replay", "restore"], "app.maps.stored"),
    "WritePath": "app.maps.writepath",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'app.maps' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
