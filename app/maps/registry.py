"""The maps a service holds: created, listed, looked up, loaded at start, quarantined, deleted."""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

from app.config import Settings
from app.storage.diskreserve import DiskReserve
from app.errors import Conflict, InsufficientStorage, Invalid, NotFound, Unavailable
from app.ops.process_setup import give_back_freed_memory
from app.maps.entry import NO_HISTORY, UNLIMITED_CELLS, MapEntry, copy_limit, history_of, now, spec_of, stored_info
from app.maps.line import shielded
from app.maps.stored import build_map, restore
from app.ops.metrics import Metrics
from app.maps.shared_grids import PlanGrids
from app.schemas import MapCreate, MapInfo
from app.storage import MapHead, NameTaken, Storage, StorageUnavailable
from app.ops.threads import Workers
from fuzzyocc import GridSpec

LOG = logging.getLogger("fuzzyrisk.maps")


class MapRegistry:
    """Named maps in memory, each backed by its rows in ``Storage``; a damaged map is set aside, not served."""

    def __init__(self, settings: Settings, storage: Storage, metrics: Metrics, workers: Workers, grids: PlanGrids,
                 reserve: DiskReserve, notify: Callable[..., None]) -> None:
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        self._workers = workers
        self._grids = grids
        self._reserve = reserve
        self._notify = notify
        self._maps: dict[str, MapEntry] = {}
        self._quarantined: dict[str, Quarantine] = {}  # map name -> why, and which incarnation, was set aside
        self._create_lock = asyncio.Lock()
        self._loading: dict[str, asyncio.Lock] = {}  # shared database: one load of a map at a time
        self._loading_cells = 0  # cells of the maps being loaded

    @property
    def held_maps(self) -> list[MapEntry]:
        """The maps in memory."""
        return list(self._maps.values())

    def batches_in_line(self) -> int:
        """Batches accepted or arriving and not yet applied, over every map held (reads catching up excluded)."""
        return sum(entry.batches_in_line for entry in self._maps.values())

    @property
    def quarantined(self) -> list[str]:
        return sorted(self._quarantined)

    async def load_all(self) -> None:
        """Load every stored map (snapshot + replay), one at a time: a start holds one map's snapshot and
        log, not every map's (377 MB of log read at once peaked at 1.1 GB).

        With a shared database, nothing: a replica loads a map at its first request (``held``).
        """
        if self.settings.shared_storage:
            return
        started = time.perf_counter()
        replayed = 0
        for name in await self._workers.run(self.storage.map_names):
            item = await self._workers.run(self.storage.load_map, name)
            if item is None:  # cannot happen: nothing else writes before the start is done
                continue
            try:
                entry = await self._workers.run(restore, item)
            except Exception as exc:  # noqa: BLE001 - any damage: this map is set aside, the others start
                self._set_aside(item.name, item.incarnation, exc)
                continue
            replayed += len(item.batches)
            self._maps[entry.name] = entry
            del item
        self.metrics.maps.set(len(self._maps))
        LOG.info(
            "maps loaded",
            extra={"fields": {"maps": len(self._maps), "replayed_batches": replayed,
                              "seconds": round(time.perf_counter() - started, 3)}},
        )

    def holding(self, name: str) -> MapEntry | None:
        """The map held here under ``name``, if any (never loads one)."""
        entry = self._maps.get(name)
        return None if entry is None or entry.deleted else entry

    def entry(self, name: str) -> MapEntry:
        """The map held under ``name`` (with a shared database, maybe behind it: see ``held``)."""
        entry = self._maps.get(name)
        if entry is None or entry.deleted:
            raise self._missing(name)
        return entry

    def _set_aside(self, name: str, incarnation: str | None, exc: Exception) -> None:
        """Quarantine a map whose stored rows cannot be loaded: its routes answer 503, the others are served."""
        self._quarantined[name] = Quarantine(str(exc), incarnation)
        LOG.error("map %s quarantined: %s", name, exc)

    def _missing(self, name: str) -> Exception:
        quarantine = self._quarantined.get(name)
        if quarantine is not None:
            return Unavailable(
                f"map {name!r} is quarantined: its stored rows are damaged ({quarantine.reason}); it is not served. "
                f"Restore the database from a backup, or drop the map with DELETE /maps/{name}"
            )
        return NotFound(f"no map named {name!r}; GET /maps lists them")

    async def held(self, name: str, *, fresh: bool = False) -> tuple[MapEntry, int]:
        """The map named ``name``, loaded if this replica does not hold it, and the newest version stored.

        With SQLite the maps are all held and nobody else writes: the newest version is the map's own. With a
        shared database (``FUZZYRISK_DATABASE_URL``) a map is loaded at its first request, and ``fresh`` asks the
        database for its newest version (one indexed row: a read must see what other replicas acknowledged). A
        map deleted, or deleted and created again, through another replica is dropped here.
        """
        if not self.settings.shared_storage:
            entry = self.entry(name)
            return entry, entry.version
        entry = self._maps.get(name)
        if entry is not None and not entry.deleted and not fresh:
            entry.last_used = time.monotonic()
            return entry, entry.version  # a write: its commit checks the map is still the stored one
        head = await self._workers.run_read(self.storage.map_head, name)
        entry = self._current_copy(name, head)
        if head is None:
            raise NotFound(f"no map named {name!r}; GET /maps lists them")
        if entry is None or entry.deleted:
            entry = await self._load(head)
        entry.last_used = time.monotonic()
        # the head read first may be another incarnation's (the map deleted and made again while it loaded):
        # its versions say nothing of this one, which was loaded with every batch it had then
        return entry, head.version if entry.incarnation == head.incarnation else entry.checked

    def _current_copy(self, name: str, head: MapHead | None) -> MapEntry | None:
        """The copy held of the stored map ``head``: a copy of a map deleted (or deleted and made again) through
        another replica is dropped, and with no map stored, its quarantine too."""
        entry = self._maps.get(name)
        if entry is not None and (head is None or entry.incarnation != head.incarnation):
            self._forget(entry, reason="deleted")
            entry = None
        if head is None:
            self._quarantined.pop(name, None)
        return entry

    async def gone(self, entry: MapEntry) -> Exception:
        """The error for a write or catch-up that found its map no longer stored as this replica holds it (deleted,
        or deleted and created again, through another replica); the stale map is dropped."""
        self._forget(entry, reason="deleted")
        head = await self._workers.run_read(self.storage.map_head, entry.name)
        if head is None:
            return NotFound(f"no map named {entry.name!r}: it was deleted (through another replica)")
        return Conflict(f"map {entry.name!r} was deleted and created again (through another replica) while this "
                        "request was under way; nothing of it was done: send it again")

    async def _load(self, head: MapHead) -> MapEntry:
        """Load a map this replica does not hold (one load per map at a time); a damaged one is quarantined here."""
        lock = self._loading.setdefault(head.name, asyncio.Lock())
        async with lock:
            entry = self._maps.get(head.name)
            if entry is not None and not entry.deleted and entry.incarnation == head.incarnation:
                return entry  # loaded by the request that held the lock before
            quarantine = self._quarantined.get(head.name)
            if quarantine is not None and quarantine.incarnation == head.incarnation:
                raise self._missing(head.name)
            cells = _cells(head.meta)
            self._make_room(cells)
            self._loading_cells += cells  # taken from the budget while loading (another load may run meanwhile)
            try:
                try:
                    stored = await self._workers.run_read(self.storage.load_map, head.name)
                    if stored is None:
                        raise NotFound(f"no map named {head.name!r}; GET /maps lists them")
                    entry = await self._workers.run(restore, stored)
                except (NotFound, StorageUnavailable):
                    raise
                except Exception as exc:  # noqa: BLE001 - any damage: this map is set aside, the others are served
                    self._set_aside(head.name, head.incarnation, exc)
                    raise self._missing(head.name) from None
            finally:
                self._loading_cells -= cells
            self._quarantined.pop(head.name, None)  # set aside as another incarnation, or repaired since
            self._maps[head.name] = entry
            self.metrics.maps.set(len(self._maps))
            LOG.info("map loaded", extra={"fields": {"map": head.name, "version": entry.version,
                                                     "replayed_batches": len(stored.batches)}})
            return entry

    def _make_room(self, cells: int) -> None:
        """Drop idle maps, least recently used first, until a map of ``cells`` fits in FUZZYRISK_MAX_TOTAL_CELLS
        beside the maps held and those being loaded."""
        used = sum(entry.map.held_cells() for entry in self._maps.values()) + self._loading_cells
        for entry in sorted(self._maps.values(), key=lambda e: e.last_used):
            if used + cells <= self.settings.max_total_cells:
                break
            if _idle(entry):
                self._forget(entry, reason="memory")
                used -= entry.map.held_cells()
        if used + cells > self.settings.max_total_cells:
            raise InsufficientStorage(
                f"this replica cannot load a map of {cells:,} cells: its maps in use hold {used:,} of its "
                f"{self.settings.max_total_cells:,} (FUZZYRISK_MAX_TOTAL_CELLS); retry later, or spread the maps "
                "over more replicas"
            )

    def _forget(self, entry: MapEntry, *, reason: str) -> None:
        """Drop a map from memory, counted as an eviction (its rows stay, unless ``reason`` is that they are gone:
        deleted through another replica)."""
        self._drop(entry, deleted=reason == "deleted")
        self.metrics.evictions.labels(reason).inc()

    def _drop(self, entry: MapEntry, *, deleted: bool) -> None:
        """Drop a map from memory; ``deleted``: its rows are gone too (its queued writers answer 404 instead of
        committing to another map's log)."""
        if self._maps.get(entry.name) is entry:  # a read may have dropped it already (found its rows gone)
            del self._maps[entry.name]
        if deleted:
            entry.deleted = True
            self._notify("map_deleted", entry.name)
        self._grids.retire(entry.uid)  # its files go now, or when the last plan on them ends
        self.metrics.maps.set(len(self._maps))

    def evict_idle(self) -> int:
        """Drop the maps no request used for ``FUZZYRISK_MAP_IDLE_S`` (shared database only); how many."""
        limit = time.monotonic() - self.settings.map_idle_s
        idle = [entry for entry in self._maps.values() if entry.last_used < limit and _idle(entry)]
        for entry in idle:
            self._forget(entry, reason="idle")
        return len(idle)

    async def list_maps(self) -> list[MapInfo]:
        """Every stored map; with a shared database, as stored (a map held here is shown as held when current)."""
        heads = await self._workers.run_read(self.storage.map_heads)
        if not self.settings.shared_storage:
            histories = {head.name: history_of(head) for head in heads}
            return [entry.info(histories.get(name, NO_HISTORY)) for name, entry in sorted(self._maps.items())]
        infos = []
        for head in heads:
            entry = self._maps.get(head.name)
            if entry is not None and entry.incarnation == head.incarnation and \
                    max(entry.version, entry.checked) >= head.version:
                infos.append(entry.info(history_of(head)))  # current (a discarded batch on top is not a version of it)
                continue
            try:
                infos.append(stored_info(head))
            except Exception as exc:  # noqa: BLE001 - unusable stored meta: listed nowhere, as at a start
                LOG.warning("map %s left out of the list: its stored metadata cannot be used (%s)", head.name, exc)
        return infos

    def held_cells(self) -> int:
        """Cells the maps held here hold in memory, together (``FUZZYRISK_MAX_TOTAL_CELLS`` counts them)."""
        return sum(entry.map.held_cells() for entry in self._maps.values())

    def _box_limit(self, meta: Mapping[str, Any]) -> int:
        """Most cells of a fixed map's box (``copy_limit``: its box bounds a whole-map read)."""
        return copy_limit(self.settings, meta["model"])

    def _check_room(self, meta: Mapping[str, Any], stored: int | None) -> None:
        """``InsufficientStorage`` when a new map would pass ``FUZZYRISK_MAX_MAPS`` or ``FUZZYRISK_MAX_TOTAL_CELLS``.

        Quarantined maps count: their rows are still stored. The others are unaffected either way. With a
        shared database, the ``stored`` maps count (every replica's), and the cells are checked when a
        replica loads the map.
        """
        held = len(self._maps) + len(self._quarantined) if stored is None else stored
        if held >= self.settings.max_maps:
            raise InsufficientStorage(f"the service holds {held} maps, its limit (FUZZYRISK_MAX_MAPS); DELETE one first")
        try:
            spec_of(meta, max_cells=self._box_limit(meta))
        except ValueError as exc:
            hint = " (FUZZYRISK_MAX_MAP_CELLS)" if "limit" in str(exc) and meta["model"] == "bayes" else ""
            raise Invalid(f"{exc}{hint}") from None
        cells = _cells(meta)
        if stored is not None:
            # a replica takes a map's memory when it loads it (``_make_room``), not when it creates it; a map that
            # no replica could load is refused now
            if cells > self.settings.max_total_cells:
                raise InsufficientStorage(
                    f"a map of {cells:,} cells does not fit in a replica's {self.settings.max_total_cells:,} "
                    "(FUZZYRISK_MAX_TOTAL_CELLS); use a coarser resolution or a smaller region"
                )
            return
        used = self.held_cells()
        if used + cells > self.settings.max_total_cells:
            raise InsufficientStorage(
                f"a map of {cells:,} cells does not fit: the maps hold {used:,} of the service's "
                f"{self.settings.max_total_cells:,} cells (FUZZYRISK_MAX_TOTAL_CELLS); use a coarser resolution, a "
                "smaller region, or DELETE a map"
            )

    async def create_map(self, request: MapCreate) -> MapInfo:
        """Create an empty map; ``Conflict`` if the name is taken, ``Invalid`` if the grid is unusable."""
        return (await self.create(request)).info(NO_HISTORY)

    async def check_new(self, request: MapCreate) -> None:
        """What ``create`` would refuse for the name and the room (409, 507, 422), before costly work for a map to be
        created (an import's image decoded). ``create`` checks again."""
        self._check_room(_meta_of(request, now()), await self._stored_count(request.name))

    async def check_name(self, name: str) -> None:
        """``Conflict`` if a map named ``name`` exists (``create`` checks again)."""
        await self._stored_count(name)

    async def _stored_count(self, name: str) -> int | None:
        """``Conflict`` if ``name`` is taken; with a shared database, how many maps are stored (every replica's)."""
        if not self.settings.shared_storage:
            if name in self._maps:
                raise Conflict(f"a map named {name!r} exists; choose another name or DELETE it first")
            return None
        names = await self._workers.run_read(self.storage.map_names)
        if name in names:
            raise Conflict(f"a map named {name!r} exists; choose another name or DELETE it first")
        return len(names)

    async def create(self, request: MapCreate) -> MapEntry:
        """Create an empty map, as ``create_map``; the map as made (with a shared database, not held: the replica
        that serves it loads it at its first request)."""
        async with self._create_lock:
            created = now()
            meta = _meta_of(request, created)
            # tells this map from another of its name made before or after it, on every replica
            meta["incarnation"] = uuid.uuid4().hex
            stored = await self._stored_count(request.name)
            self._check_room(meta, stored)  # before the map's memory is taken
            try:
                built = await self._workers.run_admin(lambda: build_map(meta, max_cells=self._box_limit(meta)))
            except ValueError as exc:  # the grid was checked by _check_room: the sensor or the engine
                raise Invalid(str(exc)) from None
            try:
                await self._workers.run_admin(self.storage.create_map, request.name, meta, created)
            except NameTaken:
                raise Conflict(f"a map named {request.name!r} exists") from None
            stale = self._maps.get(request.name)
            if stale is not None:  # a copy of a map of that name deleted through another replica
                self._forget(stale, reason="deleted")
            entry = MapEntry(meta, built, 0, 0, 0, created)
            if not self.settings.shared_storage:
                self._maps[request.name] = entry
                self.metrics.maps.set(len(self._maps))
            # with a shared database the replica that will serve the map (the load balancer's choice for
            # its name) loads it at its first request: the one that made it need not hold it
            return entry

    async def discard(self, name: str, incarnation: str | None) -> None:
        """Delete the map ``name`` if it is still the one of ``incarnation`` (an import that failed after creating
        it: nothing of it stays); any other map of that name is left alone."""
        if self.settings.shared_storage:
            await self._workers.run_admin(self._delete_rows, name, incarnation)
            entry = self._maps.get(name)
            if entry is not None and entry.incarnation == incarnation:
                self._forget(entry, reason="deleted")
            return
        entry = self._maps.get(name)
        if entry is not None and not entry.deleted and entry.incarnation == incarnation:
            await self.delete_map(name)

    async def delete_map(self, name: str) -> None:
        """Remove a map and its stored rows (after the batches that arrived before, if any).

        A quarantined map (damaged rows, found at start) is dropped with its rows.
        """
        if self.settings.shared_storage:
            head = await self._workers.run_read(self.storage.map_head, name)
            if head is None:
                self._current_copy(name, head)
                raise NotFound(f"no map named {name!r}; GET /maps lists them")
            if self._current_copy(name, head) is None:  # not held here: its rows only
                await self._workers.run_admin(self._delete_rows, name, head.incarnation)
                self._quarantined.pop(name, None)
                self._notify("map_deleted", name)
                return
        if name in self._quarantined and name not in self._maps:
            await self._workers.run_admin(self._delete_rows, name, self._quarantined[name].incarnation)
            del self._quarantined[name]
            return
        entry = self.entry(name)
        ticket = entry.line.take()
        # shielded as a batch's write is: a cancelled request must not leave the rows deleted
        # and the map still served
        await shielded(self._delete(entry, ticket))
        del entry  # the last reference: the map's memory is free, and can go back to the system
        await self._workers.run_admin(give_back_freed_memory)

    def _delete_rows(self, name: str, incarnation: str | None) -> None:
        """``storage.delete_map``; on a full disk, with the disk reserve given up first (then taken back)."""
        try:
            self.storage.delete_map(name, incarnation)
        except StorageUnavailable:
            if not self._reserve.release():
                raise
            self.storage.delete_map(name, incarnation)
        self._reserve.hold()  # once there is room again (a deletion frees pages for SQLite, not always disk)

    async def _delete(self, entry: MapEntry, ticket: int) -> None:
        try:
            await entry.line.wait_all(ticket)
            # a snapshot still being written would otherwise land after the rows are gone (or, for a map made
            # before incarnations, on a new map of the same name)
            await entry.snapshot_done()
            if entry.deleted:
                raise NotFound(f"no map named {entry.name!r}")
            await self._workers.run_admin(self._delete_rows, entry.name, entry.incarnation)
            self._drop(entry, deleted=True)
        finally:
            entry.line.done(ticket)


def _meta_of(request: MapCreate, created: str) -> dict[str, Any]:
    """A new map's stored metadata (without its incarnation): its name and settings as ``GET /maps/{name}`` shows
    them back."""
    return {**request.model_dump(mode="json"), "created": created}


class Quarantine(NamedTuple):
    """A map set aside: why, and the incarnation whose rows were damaged (another one made since loads)."""

    reason: str
    incarnation: str | None


def _cells(meta: Mapping[str, Any]) -> int:
    """Cells a map takes in memory before it has fused anything: a bayes map's whole box; a fuzzy map's none (its
    blocks come with the scans, counted once loaded: ``MapEntry.held_cells``)."""
    if meta["model"] != "bayes":
        return 0
    return GridSpec(origin=meta["origin"], size=meta["size"], resolution=meta["resolution"],
                    max_cells=UNLIMITED_CELLS).num_cells


def _idle(entry: MapEntry) -> bool:
    """No batch in the map's line or on its way, no import using it: dropping it loses nothing (its rows hold
    everything acknowledged)."""
    return entry.line.outstanding == 0 and entry.arriving == 0 and entry.users == 0
