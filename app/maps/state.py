"""A map held in memory and what the service keeps beside it: its writers' line, its grid copies, its restore.

Shared by the write path (``app.maps.writepath``), the reads (``app.reads.service``), the registry of maps
(``app.maps.registry``) and the plans (``app.plans.service``); it knows nothing of HTTP.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import io
import logging
import time
from collections.abc import Coroutine, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Protocol, TypeVar

import numpy as np

from app.scans import batches
from app.formats import etags
from app.schemas import engine_choice
from app.formats import exports
from app.maps import shared_grids
from app.schemas import DEFAULT_FRAME_ID, EngineInfo, MapInfo, PlanResult, SensorIn
from app.storage import MapHead, StoredMap
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, SensorModel, cast_work

LOG = logging.getLogger("fuzzyrisk.maps")
T = TypeVar("T")

#: Cells a stored map may have whatever ``FUZZYRISK_MAX_MAP_CELLS`` says now: a limit lowered since the map
#: was made must not lose the map
UNLIMITED_CELLS = 2**62

OccupancyMap = FuzzyMap | BayesMap


class MapObserver(Protocol):
    """Told of each change right after it happened (a live view: ``app.reads.foxglove``).

    Called on the event loop, the batch's apply lock held: a method must return at once (hand the
    work to a thread of its own) and should not raise (what it raises is logged, never answered).
    ``frame_id`` is the map's frame (``MapEntry.frame_id``), what its messages carry.
    """

    def batch_applied(self, name: str, version: int, last_scan: batches.Scan, frame_id: str) -> None: ...

    def plan_made(self, name: str, result: PlanResult, frame_id: str) -> None: ...

    def map_deleted(self, name: str) -> None: ...



def now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def npz(arrays: Mapping[str, np.ndarray]) -> bytes:
    out = io.BytesIO()
    # snapshots are mostly unknown cells: deflate shrinks them many times over
    np.savez_compressed(out, allow_pickle=False, **arrays)
    return out.getvalue()


def unnpz(payload: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(payload), allow_pickle=False) as archive:
        return {key: archive[key] for key in archive.files}


class Turns:
    """Tickets handed out in arrival order; holders pass one at a time, in ticket order.

    ``take`` is synchronous, so calling it before the first ``await`` of a request fixes the
    request's place in line. Every ticket taken must be ``done`` exactly once (``finally``),
    whether its holder ran, failed or was cancelled, or the line stops.
    """

    def __init__(self) -> None:
        self._next = 0
        self._serving = 0
        self._finished: set[int] = set()
        self._waiters: dict[int, asyncio.Future[None]] = {}

    def take(self) -> int:
        ticket = self._next
        self._next += 1
        return ticket

    @property
    def outstanding(self) -> int:
        """Tickets taken and not yet done."""
        return self._next - self._serving - len(self._finished)

    async def wait(self, ticket: int) -> None:
        """Return once every earlier ticket is done."""
        if ticket == self._serving:
            return
        waiter = asyncio.get_running_loop().create_future()
        self._waiters[ticket] = waiter
        try:
            await waiter
        finally:
            del self._waiters[ticket]

    def done(self, ticket: int) -> None:
        """Give the turn up (a ticket finished early, e.g. a refused batch, is skipped when its turn comes).

        Idempotent: a ticket given up again is ignored.
        """
        if ticket < self._serving or ticket in self._finished:
            return
        self._finished.add(ticket)
        while self._serving in self._finished:
            self._finished.discard(self._serving)
            self._serving += 1
        waiter = self._waiters.get(self._serving)
        if waiter is not None and not waiter.done():
            waiter.set_result(None)


class Line:
    """A map's writers in arrival order through two stages, each passed in ticket order: commit, then apply.

    A ticket enters a stage once every earlier ticket has left it. A batch leaves the commit
    stage as soon as it is durable, so the next batch's fsync overlaps this one's fusion.
    ``done`` leaves both stages (``finally``: whatever happened to the holder).
    """

    def __init__(self) -> None:
        self.commit = Turns()
        self.apply = Turns()

    @property
    def outstanding(self) -> int:
        """Holders in line: taken, not yet out of the apply stage."""
        return self.apply.outstanding

    def take(self) -> int:
        ticket = self.commit.take()
        if self.apply.take() != ticket:  # both are only ever taken here, together
            raise RuntimeError("commit and apply tickets out of step")
        return ticket

    async def wait_all(self, ticket: int) -> None:
        """Return once every earlier ticket has left both stages (the map is this holder's alone)."""
        await self.commit.wait(ticket)
        await self.apply.wait(ticket)

    def done(self, ticket: int) -> None:
        self.commit.done(ticket)
        self.apply.done(ticket)


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
    last_scan: batches.Scan | None = None
    last_view: batches.ScanView | None = None
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
    def spec(self) -> GridSpec:
        return self.map.spec

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
        return GridStamp(self.spec, self.version, self.frame_id, self.updated, self.etag_seed)

    @functools.cached_property
    def engine_info(self) -> EngineInfo | None:
        """The fuzzy engine as ``MapInfo`` shows it (once: a map's engine never changes)."""
        if not isinstance(self.map, FuzzyMap):
            return None
        return EngineInfo(**engine_choice.describe(self.map.engine))

    def info(self) -> MapInfo:
        return map_info(self.meta, self.spec, self.engine_info, scans_fused=self.scans_fused, version=self.version,
                        updated=self.updated)


def map_info(meta: Mapping[str, Any], spec: GridSpec, engine: EngineInfo | None, *, scans_fused: int, version: int,
             updated: str) -> MapInfo:
    """What ``GET /maps/{name}`` shows of a map, held in memory or only stored."""
    return MapInfo(
        name=str(meta["name"]),
        dimensions=spec.ndim,
        resolution=spec.resolution,
        origin=list(spec.origin),
        size=[float(f"{n * spec.resolution:.12g}") for n in spec.shape],  # as built: whole cells
        shape=list(spec.shape),
        model=meta["model"],
        sensor=SensorIn(**meta["sensor"]),
        engine=engine,
        frame_id=str(meta.get("frame_id", DEFAULT_FRAME_ID)),
        scans_fused=scans_fused,
        version=version,
        created=meta["created"],
        updated=updated,
    )


def stored_info(head: MapHead) -> MapInfo:
    """``map_info`` of a map this replica does not hold, from its stored row (no map built)."""
    spec = GridSpec(origin=head.meta["origin"], size=head.meta["size"], resolution=head.meta["resolution"],
                    max_cells=UNLIMITED_CELLS)
    engine = (EngineInfo(**engine_choice.describe(engine_choice.from_meta(head.meta)))
              if head.meta["model"] == "fuzzy" else None)
    return map_info(head.meta, spec, engine, scans_fused=head.scans, version=head.version, updated=head.updated)


@dataclass(frozen=True)
class GridStamp:
    """What a read of one version of a map carries besides its cells: the version, its frame, time and ETag."""

    spec: GridSpec
    version: int
    frame_id: str = DEFAULT_FRAME_ID
    #: when the map reached this version (its last batch's ``updated``; its creation at version 0), ISO 8601
    updated: str = ""
    #: ``MapEntry.etag_seed``
    etag_seed: str = ""

    def etag(self, variant: Mapping[str, Any]) -> str:
        """The strong ETag of one representation of this version (``etags.entity_tag``)."""
        return etags.entity_tag(self.etag_seed, self.version, variant)


@dataclass(frozen=True)
class GridSnapshot:
    """Copies of a map's risk and observed arrays at one version, with what its outputs carry."""

    spec: GridSpec
    version: int
    risk: np.ndarray
    observed: np.ndarray
    frame_id: str = DEFAULT_FRAME_ID
    #: when the map reached this version (its last batch's ``updated``; its creation at version 0), ISO 8601
    updated: str = ""
    #: ``MapEntry.etag_seed``
    etag_seed: str = ""

    def etag(self, variant: Mapping[str, Any]) -> str:
        """``GridStamp.etag`` of this version."""
        return self.stamp().etag(variant)

    def stamp(self) -> GridStamp:
        """The ``GridStamp`` of the version these arrays are of."""
        return GridStamp(self.spec, self.version, self.frame_id, self.updated, self.etag_seed)

    def planar(self, z_min: float | None, z_max: float | None) -> tuple[np.ndarray, np.ndarray]:
        """2-D risk and observed: the map itself, or a 3-D map projected over ``[z_min, z_max]``."""
        if self.spec.ndim == 2:
            return self.risk, self.observed
        return exports.project_z(
            self.risk, self.observed, origin_z=self.spec.origin[2], resolution=self.spec.resolution,
            z_min=z_min, z_max=z_max,
        )


def build_map(meta: Mapping[str, Any], *, max_cells: int) -> OccupancyMap:
    """An empty map as ``meta`` describes it (a new map is built from its meta too: what is stored is what runs)."""
    spec = GridSpec(origin=meta["origin"], size=meta["size"], resolution=meta["resolution"], max_cells=max_cells)
    sensor = SensorModel(**meta["sensor"])
    if meta["model"] == "fuzzy":
        return FuzzyMap(spec, sensor, engine_choice.from_meta(meta))
    return BayesMap(spec, sensor)


def restore(stored: StoredMap, up_to: int | None = None) -> MapEntry:
    """A map from its snapshot and the batches after it (replayed in order: bit-identical risk).

    ``up_to``: replay only the batches up to that version (a live map's rebuild: later batches
    may be committed and still waiting for their turn to be applied).
    """
    if stored.damage:
        raise RuntimeError(f"map {stored.name!r}: {'; '.join(stored.damage)}")
    try:
        built = build_map(stored.meta, max_cells=UNLIMITED_CELLS)
    except ValueError as exc:
        raise RuntimeError(f"map {stored.name!r}: its stored metadata cannot be used ({exc}); the database "
                           "needs repair") from exc
    if stored.snapshot is not None:
        arrays = unnpz(stored.snapshot)
        if isinstance(built, FuzzyMap):
            built = FuzzyMap.from_arrays(built.spec, built.sensor, arrays, built.engine)
        else:
            built = BayesMap.from_arrays(built.spec, built.sensor, arrays)
    entry = MapEntry(
        dict(stored.meta), built, stored.snapshot_version, stored.snapshot_version, built.scans_fused,
        stored.stamps.get(stored.snapshot_version, stored.updated),
    )
    progress = replay(entry.map, stored, after=entry.version, up_to=up_to)
    entry.version, entry.scans_fused, entry.updated = progress.version or entry.version, built.scans_fused, \
        progress.updated or entry.updated
    entry.last_scan = progress.last_scan
    entry.log.extend(progress.log)
    # versions up to the stored one that were not replayed are discarded batches (tombstones)
    entry.checked = stored.version if up_to is None else min(stored.version, up_to)
    return entry


@dataclass
class Replayed:
    """What ``replay`` brought a map to: its newest version replayed (0: none), that batch's ``updated``, ..."""

    version: int = 0
    updated: str = ""
    last_scan: batches.Scan | None = None
    #: (version, bytes, cells walked) of the batches replayed, for ``MapEntry.log``
    log: list[tuple[int, int, int]] = field(default_factory=list)


def replay(built: OccupancyMap, stored: StoredMap, *, after: int, up_to: int | None = None) -> Replayed:
    """Fuse ``stored``'s batches above version ``after`` (and at most ``up_to``) into ``built``, in order."""
    progress = Replayed()
    for version, payload in stored.batches:
        if version <= after:
            continue
        if up_to is not None and version > up_to:
            break
        try:
            scans = batches.decode(payload)
        except batches.CorruptBatch as exc:
            # an acknowledged batch: never dropped silently; the service refuses to start and says where
            raise RuntimeError(f"map {stored.name!r}: stored batch {version} is corrupt ({exc}); the database "
                               f"needs repair (restore a backup, or delete that row to drop the batch)") from exc
        progress.log.append((version, len(payload), cast_work(built.spec, scans)))
        try:
            built.integrate_batch(scans)
        except ValueError:
            # cannot happen for a batch that was acknowledged (it was applied before the 200)
            LOG.exception("map %s: batch %d cannot be replayed; skipped", stored.name, version)
            continue
        progress.version, progress.last_scan = version, scans[-1]
        progress.updated = stored.stamps.get(version, stored.updated)
    return progress

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


async def shielded(work: Coroutine[Any, Any, T]) -> T:
    """Run ``work`` to its end even if the awaiting request is cancelled (a client gone away)."""
    task = asyncio.ensure_future(work)
    task.add_done_callback(_retrieve)
    return await asyncio.shield(task)


def _retrieve(task: asyncio.Future[Any]) -> None:
    """Mark a shielded task's exception as seen: its request may have been cancelled, and the error
    reached the client (or nobody) through the shield, not through this task."""
    if not task.cancelled():
        task.exception()

