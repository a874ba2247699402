"""A map held in memory (``MapEntry``), with what the service knows about it, and what ``GET /maps/{name}`` shows.

Shared by the write path (``app.maps.writepath``), the reads (``app.reads.service``), the registry of maps
(``app.maps.registry``) and the plans (``app.plans.service``); it knows nothing of HTTP.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Protocol

from app.config import Settings
from app.errors import Conflict
from app.formats import etags
from app.maps import shared_grids
from app.maps.line import Line
from app.maps.snapshot import GridStamp
from app.scans import Scan, ScanView
from app.schemas import DEFAULT_FRAME_ID, MapCreate, MapHistory, MapInfo, PlanResult
from app.schemas import engine_choice
from app.schemas.common import ros_time_of_ns
from app.storage import MapHead
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LatticeSpec
from fuzzyocc.config import DEFAULT_MAX_CELLS


#: Cells a stored map may have whatever ``FUZZYRISK_MAX_MAP_CELLS`` says now: a limit lowered since the map
#: was made must not lose the map
UNLIMITED_CELLS = 2**62

OccupancyMap = FuzzyMap | BayesMap


def copy_limit(settings: Settings, model: str = "fuzzy") -> int:
    """Most cells of one dense copy of a map: a fixed map's box (its whole-map reads), and a read or a plan's grid
    of a growing map. A bayes map holds its whole box (``FUZZYRISK_MAX_MAP_CELLS``); a fuzzy map holds only the
    blocks its scans reached, so a copy of it is bounded apart, as the largest box (``DEFAULT_MAX_CELLS`` at least)."""
    if model == "bayes":
        return settings.max_map_cells
    return max(settings.max_map_cells, DEFAULT_MAX_CELLS)


class MapObserver(Protocol):
    """Told of each change right after it happened (a live view: ``app.reads.foxglove``).

    Called on the event loop, the batch's apply lock held: a method must return at once (hand the
    work to a thread of its own) and should not raise (what it raises is logged, never answered).
    ``frame_id`` is the map's frame (``MapEntry.frame_id``), what its messages carry; ``last_scan`` the last
    scan fused, None before the first (an imported map's first batch holds none).
    """

    def batch_applied(self, name: str, version: int, last_scan: Scan | None, frame_id: str) -> None: ...

    def plan_made(self, name: str, result: PlanResult, frame_id: str) -> None: ...

    def map_deleted(self, name: str) -> None: ...


def now() -> str:
    """The time now as a map's ``updated`` carries it (ISO 8601, UTC, milliseconds)."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


@dataclass
class MapEntry:
    """A map held in memory, with what the service knows about it."""

    meta: dict[str, Any]
    map: OccupancyMap
    version: int
    snapshot_version: int
    scans_fused: int
    updated: str
    line: Line = field(default_factory=Line)
    apply_lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    #: the last scan fused; its view for the web page is built when first asked for
    last_scan: Scan | None = None
    last_view: ScanView | None = None
    #: version at the last failed snapshot attempt (the next attempt waits snapshot_every batches more)
    snapshot_failed_version: int = 0
    deleted: bool = False
    #: uploads for this map whose bodies are still arriving (they count against its line: ``receiving``)
    arriving: int = 0
    #: (version, bytes, cells walked) of each batch in the log after the latest snapshot: the log is bounded
    #: in bytes (the disk) and in cells (the replay at a restart) too
    log: collections.deque[tuple[int, int, int]] = field(default_factory=collections.deque)
    #: names this map among every map the process held (a deleted map's name may come back; its uid does not)
    uid: int = field(default_factory=shared_grids.new_uid)
    #: ``time.monotonic()`` of the last request that used the map (a replica drops maps idle for long)
    last_used: float = field(default_factory=time.monotonic)
    #: versions this replica committed and has not applied yet (a read need not wait for them: not acknowledged)
    inflight: set[int] = field(default_factory=set)
    #: the newest stored version caught up to: versions up to it that were not applied are discarded batches
    checked: int = 0
    #: requests that hold the map across awaits without a place in its line (a bag import between its batches):
    #: the map is not dropped from memory meanwhile
    users: int = 0
    #: reads waiting in the line to apply other replicas' batches (not batches: ``_admit`` leaves them out)
    catching_up: int = 0
    #: the snapshot being taken beside the line, if any (``WritePath._snapshot_beside``)
    snapshotting: asyncio.Task[None] | None = None

    async def snapshot_done(self) -> None:
        """Wait for the snapshot being taken, if any (it logs its own failure; its cancellation is not ours)."""
        if self.snapshotting is not None:
            await asyncio.wait([self.snapshotting])

    @property
    def batches_in_line(self) -> int:
        """Batches in its line or arriving, not yet applied (reads catching up are not batches)."""
        return self.line.outstanding - self.catching_up + self.arriving

    @property
    def incarnation(self) -> str | None:
        """Tells this map apart from another stored under its name before or after it (None: a map from before)."""
        value = self.meta.get("incarnation")
        return None if value is None else str(value)

    @property
    def name(self) -> str:
        return str(self.meta["name"])

    @property
    def spec(self) -> GridSpec | LatticeSpec:
        """The map's geometry: a fixed map's box, a growing map's lattice."""
        return self.map.spec

    def read_spec(self) -> GridSpec:
        """The cells a read covers: a fixed map's box, a growing map's bounds (read it under ``apply_lock``).

        ``Conflict`` for a growing map that has observed nothing yet: it has no cell to show."""
        window = self.map.window()
        if window is None:
            raise Conflict(f"map {self.name!r} is a growing map that has observed nothing yet: its bounds are null "
                           "until the first scan reaches a cell")
        return self.map.spec if isinstance(self.map.spec, GridSpec) else window.spec()

    @property
    def frame_id(self) -> str:
        """The map's ROS frame (maps stored before frames could be chosen are in ``map``)."""
        return str(self.meta.get("frame_id", DEFAULT_FRAME_ID))

    @functools.cached_property
    def etag_seed(self) -> str:
        """Tells this map apart from another of the same name, across restarts (``etags.map_seed``)."""
        return etags.map_seed(self.meta)

    def stamp(self) -> GridStamp:
        """This version's ``GridStamp`` (read it under ``apply_lock``, with the cells it stamps)."""
        return GridStamp(self.read_spec(), self.version, self.frame_id, self.updated, self.etag_seed)

    @functools.cached_property
    def engine_shown(self) -> engine_choice.EngineChoice | None:
        """The fuzzy engine as ``MapInfo`` shows it (once: a map's engine never changes)."""
        if not isinstance(self.map, FuzzyMap):
            return None
        return engine_choice.shown(self.map.engine)

    def info(self, history: MapHistory) -> MapInfo:
        """What ``GET /maps/{name}`` shows of the map, with its ``history`` as stored (``history_of``)."""
        bounds = self.map.bounds()
        # a PATCH changes forget_beyond after the meta was stored: the map holds the setting as it is now
        meta = {**self.meta, "forget_beyond": self.map.forget_beyond} if isinstance(self.map, FuzzyMap) else self.meta
        return map_info(meta, self.spec, self.engine_shown, scans_fused=self.scans_fused, version=self.version,
                        updated=self.updated, bounds=None if bounds is None else bounds.spec(),
                        held_cells=self.map.held_cells(), history=history)


#: The history of a map just made: nothing stored yet.
NO_HISTORY = MapHistory(from_version=0, from_stamp=None, bytes=0, scans=0)


def history_of(head: MapHead | None) -> MapHistory:
    """A map's history as its stored row counts it (``NO_HISTORY`` when there is no row)."""
    if head is None:
        return NO_HISTORY
    stamp = None if head.from_stamp_ns is None else ros_time_of_ns(head.from_stamp_ns)
    return MapHistory(from_version=head.base_version, from_stamp=stamp, bytes=head.history_bytes,
                      scans=head.history_scans)


def map_info(meta: Mapping[str, Any], spec: GridSpec | LatticeSpec, engine: engine_choice.EngineChoice | None, *,
             scans_fused: int, version: int, updated: str, bounds: GridSpec | None,
             held_cells: int | None, history: MapHistory) -> MapInfo:
    """What ``GET /maps/{name}`` shows of a map, held in memory or only stored.

    Its settings as its meta stores them (a setting the map was made before: its default), the grid
    as built (``size``: whole cells; a growing map's: its ``bounds``), the engine as
    ``engine_choice.shown``, then the facts.
    """
    settings = {key: meta[key] for key in MapCreate.model_fields if key in meta}
    box = spec if isinstance(spec, GridSpec) else bounds
    return MapInfo.model_validate({
        **settings,
        "dimensions": spec.ndim,
        "resolution": spec.resolution,
        "extent": "fixed" if isinstance(spec, GridSpec) else "growing",
        "origin": None if box is None else list(box.origin),
        "size": None if box is None else list(box.built_size),
        "engine": engine,
        "shape": None if box is None else list(box.shape),
        "bounds": None if bounds is None else {"min": list(bounds.origin), "max": list(bounds.upper)},
        "held_cells": held_cells,
        "scans_fused": scans_fused,
        "version": version,
        "created": meta["created"],
        "updated": updated,
        "history": history,
    })


def spec_of(meta: Mapping[str, Any], *, max_cells: int) -> GridSpec | LatticeSpec:
    """A map's geometry as its meta stores it: a box, or the lattice of a growing map (maps stored before growing
    maps existed have a box)."""
    if meta.get("extent") == "growing":
        return LatticeSpec(int(meta["dimensions"]), float(meta["resolution"]))
    return GridSpec(origin=meta["origin"], size=meta["size"], resolution=meta["resolution"], max_cells=max_cells)


def stored_info(head: MapHead) -> MapInfo:
    """``map_info`` of a map this replica does not hold, from its stored row (no map built: no bounds, no cells)."""
    spec = spec_of(head.meta, max_cells=UNLIMITED_CELLS)
    engine = engine_choice.shown(engine_choice.from_meta(head.meta)) if head.meta["model"] == "fuzzy" else None
    return map_info(head.meta, spec, engine, scans_fused=head.scans, version=head.version, updated=head.updated,
                    bounds=None, held_cells=None, history=history_of(head))


@contextlib.contextmanager
def in_use(entry: MapEntry) -> Iterator[MapEntry]:
    """Hold ``entry`` in memory across awaits outside its line (``MapEntry.users``)."""
    entry.users += 1
    try:
        yield entry
    finally:
        entry.users -= 1


def is_current(entry: MapEntry, version: int) -> bool:
    """Is ``version`` still the version of the map that ``entry`` holds?"""
    return not entry.deleted and entry.version == version
