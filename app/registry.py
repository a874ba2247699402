"""The maps a service holds: created, listed, looked up, loaded at start, quarantined, deleted."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Mapping
from typing import Any

from app import engines
from app.config import Settings
from app.diskreserve import DiskReserve
from app.errors import Conflict, InsufficientStorage, Invalid, NotFound, Unavailable
from app.mapstate import MapEntry, build_map, now, restore, shielded
from app.metrics import Metrics
from app.plangrids import PlanGrids
from app.schemas import MapCreate, MapInfo
from app.storage import NameTaken, Storage, StorageUnavailable
from app.workers import Workers
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
        self._quarantined: dict[str, str] = {}  # map name -> why it was set aside at start
        self._create_lock = asyncio.Lock()

    @property
    def held(self) -> list[MapEntry]:
        """The maps in memory."""
        return list(self._maps.values())

    @property
    def quarantined(self) -> list[str]:
        return sorted(self._quarantined)

    async def load_all(self) -> None:
        """Load every stored map (snapshot + replay), one at a time: a start holds one map's snapshot and
        log, not every map's (issue 11: 377 MB of log read at once peaked at 1.1 GB)."""
        started = time.perf_counter()
        replayed = 0
        for name in await self._workers.run(self.storage.map_names):
            item = await self._workers.run(self.storage.load_map, name)
            if item is None:  # cannot happen: nothing else writes before the start is done
                continue
            try:
                entry = await self._workers.run(restore, item)
            except Exception as exc:  # noqa: BLE001 - any damage: this map is set aside, the others start
                self._quarantined[item.name] = str(exc)
                LOG.error("map %s quarantined: %s", item.name, exc)
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

    def entry(self, name: str) -> MapEntry:
        entry = self._maps.get(name)
        if entry is None or entry.deleted:
            reason = self._quarantined.get(name)
            if reason is not None:
                raise Unavailable(
                    f"map {name!r} is quarantined: its stored rows are damaged ({reason}); it is not served. "
                    f"Restore the database from a backup, or drop the map with DELETE /maps/{name}"
                )
            raise NotFound(f"no map named {name!r}; GET /maps lists them")
        return entry

    def list_maps(self) -> list[MapInfo]:
        return [entry.info() for _, entry in sorted(self._maps.items())]

    def get_map(self, name: str) -> MapInfo:
        return self.entry(name).info()

    def map_uid(self, name: str) -> int:
        """Tells the map now named ``name`` apart from an earlier or later map of that name (``MapEntry.uid``)."""
        return self.entry(name).uid

    def _check_room(self, meta: Mapping[str, Any]) -> None:
        """``InsufficientStorage`` when a new map would pass ``FUZZYRISK_MAX_MAPS`` or ``FUZZYRISK_MAX_TOTAL_CELLS``.

        Quarantined maps count: their rows are still stored. The others are unaffected either way.
        """
        held = len(self._maps) + len(self._quarantined)
        if held >= self.settings.max_maps:
            raise InsufficientStorage(f"the service holds {held} maps, its limit (FUZZYRISK_MAX_MAPS); DELETE one first")
        try:
            cells = GridSpec(origin=meta["origin"], size=meta["size"], resolution=meta["resolution"],
                             max_cells=self.settings.max_map_cells).num_cells
        except ValueError as exc:
            hint = " (FUZZYRISK_MAX_MAP_CELLS)" if "limit" in str(exc) else ""
            raise Invalid(f"{exc}{hint}") from None
        used = sum(entry.spec.num_cells for entry in self._maps.values())
        if used + cells > self.settings.max_total_cells:
            raise InsufficientStorage(
                f"a map of {cells:,} cells does not fit: the maps hold {used:,} of the service's "
                f"{self.settings.max_total_cells:,} cells (FUZZYRISK_MAX_TOTAL_CELLS); use a coarser resolution, a "
                "smaller region, or DELETE a map"
            )

    async def create_map(self, request: MapCreate) -> MapInfo:
        """Create an empty map; ``Conflict`` if the name is taken, ``Invalid`` if the grid is unusable."""
        async with self._create_lock:
            if request.name in self._maps:
                raise Conflict(f"a map named {request.name!r} exists; choose another name or DELETE it first")
            created = now()
            meta = {
                "name": request.name,
                "origin": list(request.origin),
                "size": list(request.size),
                "resolution": request.resolution,
                "model": request.model,
                "sensor": request.sensor.model_dump(),
                "frame_id": request.frame_id,
                "created": created,
            }
            if request.model == "fuzzy":
                meta["engine"] = engines.to_meta(request.engine or engines.default())
            self._check_room(meta)  # before the map's memory is taken
            try:
                built = await self._workers.run(lambda: build_map(meta, max_cells=self.settings.max_map_cells))
            except ValueError as exc:  # the grid was checked by _check_room: the sensor or the engine
                raise Invalid(str(exc)) from None
            try:
                await self._workers.run(self.storage.create_map, request.name, meta, created)
            except NameTaken:
                raise Conflict(f"a map named {request.name!r} exists") from None
            entry = MapEntry(meta, built, 0, 0, 0, created)
            self._maps[request.name] = entry
            self.metrics.maps.set(len(self._maps))
            return entry.info()

    async def delete_map(self, name: str) -> None:
        """Remove a map and its stored rows (after the batches that arrived before, if any).

        A quarantined map (damaged rows, found at start) is dropped with its rows.
        """
        if name in self._quarantined and name not in self._maps:
            await self._workers.run(self._delete_rows, name)
            del self._quarantined[name]
            return
        entry = self.entry(name)
        ticket = entry.line.take()
        # shielded as a batch's write is: a cancelled request must not leave the rows deleted
        # and the map still served
        await shielded(self._delete(entry, ticket))

    def _delete_rows(self, name: str) -> None:
        """``storage.delete_map``; on a full disk, with the disk reserve given up first (then taken back)."""
        try:
            self.storage.delete_map(name)
        except StorageUnavailable:
            if not self._reserve.release():
                raise
            self.storage.delete_map(name)
        self._reserve.hold()  # once there is room again (a deletion frees pages for SQLite, not always disk)

    async def _delete(self, entry: MapEntry, ticket: int) -> None:
        try:
            await entry.line.wait_all(ticket)
            if entry.deleted:
                raise NotFound(f"no map named {entry.name!r}")
            await self._workers.run(self._delete_rows, entry.name)
            entry.deleted = True
            del self._maps[entry.name]
            self._grids.retire(entry.uid)  # its files go now, or when the last plan on them ends
            self._notify("map_deleted", entry.name)
        finally:
            entry.line.done(ticket)
        self.metrics.maps.set(len(self._maps))

    # ---------------------------------------------------------------- scans
