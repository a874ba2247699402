"""The service's domain functions: the only bridge from HTTP to ``fuzzyocc`` and ``planning``.

Concurrency: each map has these orderings.

* ``line`` (writers: batches, delete, the final snapshot): a batch takes a ticket
  the moment it arrives, is parsed and validated with no lock held (so batch k+1
  parses while batch k fuses; in a parsing thread, or on the event loop when the
  body is small: ``INLINE_PARSE_BYTES``), then passes two stages in ticket
  order: *commit* (made durable) and *apply* (fused into the map). Batch k+1 may
  commit while batch k is still fusing, so the fsync is off the map's critical
  path; both stages still go in arrival order, whatever order parsing finishes in.
  A batch refused by validation gives its turns up. Delete and the final snapshot
  wait for both stages (every earlier batch committed and applied).
* ``apply_lock`` (short): held while the map object is used, i.e. while a batch is
  applied, while a snapshot copies the arrays (compression and the write happen
  after, holding the apply turn only) and while a reader (risk, query, plan) copies.
  A reader waits for at most the batch being applied, never behind the queued ones,
  and never sees a half-applied batch or a version that does not match the arrays.

The CPU work runs off the event loop: parsing and validation of big bodies in
parsing threads, fusion in the fusion threads (numpy and numba release the GIL), commits in one
writer thread (``app.committer``: batches queued meanwhile, from any map, share a
transaction), plans in worker processes. Different maps proceed in parallel.

Durability: a batch is parsed and validated completely, then committed (fsync)
with the version it brings the map to, then applied, then acknowledged. A store
that cannot take the commit (full disk, read-only directory) raises
``StorageUnavailable`` before anything is applied. Once parsed, a batch is
committed and applied even if its request is cancelled (a client gone away): a
batch committed but not applied would make the map differ from its replay. A batch
that cannot be applied after its commit (a bug, memory) is removed from the log and
answered 500; its version is not reused (a later batch may have committed with
the next one meanwhile), so the map's version then skips one number. A snapshot is only an optimisation of restarts (the
batch log already holds every acknowledged batch), so a failed snapshot is logged,
counted and retried later, never answered as an error.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import io
import logging
import os
import time
from collections.abc import Callable, Coroutine, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Literal, Protocol, TypeVar

import numpy as np
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from app import batches, conditional, engines, exports, plangrids, rosmsgs, rosout, rostypes, warmup
from app.committer import GroupCommitter
from app.config import Settings
from app.diskreserve import DiskReserve
from app.errors import (
    Conflict,
    InsufficientStorage,
    Invalid,
    NotFound,
    PlanRejected,
    TooLarge,
    Unavailable,
    UnsupportedMediaType,
)
from app.metrics import Metrics
from app.plangrids import Lease, PlanGrids
from app.planworker import PlanPool, run_plan, run_shared_plan
from app.schemas import (
    DEFAULT_FRAME_ID,
    BatchResult,
    EngineInfo,
    LastScan,
    MapCreate,
    MapInfo,
    OccupancyGrid,
    PlanRequest,
    PlanResult,
    Readiness,
    RiskGridJSON,
    RiskValues,
    ScanBatch,
    ScanQuery,
    SensorIn,
)
from app.storage import BatchRecord, NameTaken, Storage, StorageUnavailable, StoredMap
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, SensorModel, cast_work
from planning.budget import wall_clock_limit
from planning.planners import planner_spec

LOG = logging.getLogger("fuzzyrisk.maps")
T = TypeVar("T")

OccupancyMap = FuzzyMap | BayesMap


class MapObserver(Protocol):
    """Told of each change right after it happened (a live view: ``app.foxglove_live``).

    Called on the event loop, the batch's apply lock held: a method must return at once (hand the
    work to a thread of its own) and should not raise (what it raises is logged, never answered).
    ``frame_id`` is the map's frame (``MapEntry.frame_id``), what its messages carry.
    """

    def batch_applied(self, name: str, version: int, last_scan: batches.Scan, frame_id: str) -> None: ...

    def plan_made(self, name: str, result: PlanResult, frame_id: str) -> None: ...

    def map_deleted(self, name: str) -> None: ...


#: Above this many cells the JSON risk grid is refused (use format=npy or png).
MAX_JSON_CELLS = 4_000_000
#: Most pixels of one PNG.
MAX_PNG_PIXELS = 64_000_000
#: Grace added to a plan's time limit before its worker is presumed stuck: setup, dilation, dense check.
PLAN_GRACE_S = 20.0
#: Bodies up to this size are parsed on the event loop rather than in a parsing thread: their parse
#: (pydantic holds the GIL either way, so the loop waits for it wherever it runs) takes well under a
#: millisecond, less than the two thread switches of a trip through the parsing pool.
INLINE_PARSE_BYTES = 128 * 1024


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def _npz(arrays: Mapping[str, np.ndarray]) -> bytes:
    out = io.BytesIO()
    # snapshots are mostly unknown cells: deflate shrinks them many times over
    np.savez_compressed(out, allow_pickle=False, **arrays)
    return out.getvalue()


def _unnpz(payload: bytes) -> dict[str, np.ndarray]:
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
    #: version of the last batch committed (``version`` is that of the last one applied: readers see that)
    committed: int = 0
    #: the last scan fused; its view for the web page is built when first asked for
    last_scan: batches.Scan | None = None
    last_view: batches.ScanView | None = None
    #: version at the last failed snapshot attempt (the next attempt waits snapshot_every batches more)
    snapshot_failed_version: int = 0
    deleted: bool = False
    #: uploads for this map whose bodies are still arriving (they count against its line: ``receiving``)
    arriving: int = 0
    #: (version, bytes) of each batch in the log after the latest snapshot: the log is bounded in bytes too
    log: collections.deque[tuple[int, int]] = field(default_factory=collections.deque)
    #: names this map among every map the process held (a deleted map's name may come back; its uid does not)
    uid: int = field(default_factory=plangrids.new_uid)

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
        """Tells this map apart from another of the same name, across restarts (``conditional.map_seed``)."""
        return conditional.map_seed(self.meta)

    @functools.cached_property
    def engine_info(self) -> EngineInfo | None:
        """The fuzzy engine as ``MapInfo`` shows it (once: a map's engine never changes)."""
        if not isinstance(self.map, FuzzyMap):
            return None
        return EngineInfo(**engines.describe(self.map.engine))

    def info(self) -> MapInfo:
        spec = self.spec
        return MapInfo(
            name=self.name,
            dimensions=spec.ndim,
            resolution=spec.resolution,
            origin=list(spec.origin),
            size=[float(f"{n * spec.resolution:.12g}") for n in spec.shape],  # as built: whole cells
            shape=list(spec.shape),
            model=self.meta["model"],
            sensor=SensorIn(**self.meta["sensor"]),
            engine=self.engine_info,
            frame_id=self.frame_id,
            scans_fused=self.scans_fused,
            version=self.version,
            created=self.meta["created"],
            updated=self.updated,
        )


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
        """The strong ETag of one representation of this version (``conditional.entity_tag``)."""
        return conditional.entity_tag(self.etag_seed, self.version, variant)

    def planar(self, z_min: float | None, z_max: float | None) -> tuple[np.ndarray, np.ndarray]:
        """2-D risk and observed: the map itself, or a 3-D map projected over ``[z_min, z_max]``."""
        if self.spec.ndim == 2:
            return self.risk, self.observed
        return exports.project_z(
            self.risk, self.observed, origin_z=self.spec.origin[2], resolution=self.spec.resolution,
            z_min=z_min, z_max=z_max,
        )


def _build_map(meta: Mapping[str, Any], *, max_cells: int) -> OccupancyMap:
    """An empty map as ``meta`` describes it (a new map is built from its meta too: what is stored is what runs)."""
    spec = GridSpec(origin=meta["origin"], size=meta["size"], resolution=meta["resolution"], max_cells=max_cells)
    sensor = SensorModel(**meta["sensor"])
    if meta["model"] == "fuzzy":
        return FuzzyMap(spec, sensor, engines.from_meta(meta))
    return BayesMap(spec, sensor)


def _restore(stored: StoredMap, up_to: int | None = None) -> MapEntry:
    """A map from its snapshot and the batches after it (replayed in order: bit-identical risk).

    ``up_to``: replay only the batches up to that version (a live map's rebuild: later batches
    may be committed and still waiting for their turn to be applied).
    """
    if stored.damage:
        raise RuntimeError(f"map {stored.name!r}: {'; '.join(stored.damage)}")
    unlimited = 2**62  # a limit lowered since the map was made must not lose the map
    try:
        built = _build_map(stored.meta, max_cells=unlimited)
    except ValueError as exc:
        raise RuntimeError(f"map {stored.name!r}: its stored metadata cannot be used ({exc}); the database "
                           "needs repair") from exc
    if stored.snapshot is not None:
        arrays = _unnpz(stored.snapshot)
        if isinstance(built, FuzzyMap):
            built = FuzzyMap.from_arrays(built.spec, built.sensor, arrays, built.engine)
        else:
            built = BayesMap.from_arrays(built.spec, built.sensor, arrays)
    entry = MapEntry(
        dict(stored.meta), built, stored.snapshot_version, stored.snapshot_version, built.scans_fused, stored.updated
    )
    for version, payload in stored.batches:
        if up_to is not None and version > up_to:
            break
        try:
            scans = batches.decode(payload)
        except batches.CorruptBatch as exc:
            # an acknowledged batch: never dropped silently; the service refuses to start and says where
            raise RuntimeError(f"map {entry.name!r}: stored batch {version} is corrupt ({exc}); the database "
                               f"needs repair (restore a backup, or delete that row to drop the batch)") from exc
        try:
            built.integrate_batch(scans)
        except ValueError:
            # cannot happen for a batch that was acknowledged (it was applied before the 200)
            LOG.exception("map %s: batch %d cannot be replayed; skipped", entry.name, version)
            continue
        entry.version = version
        entry.last_scan = scans[-1]
    entry.log.extend((version, len(payload)) for version, payload in stored.batches
                     if up_to is None or version <= up_to)
    entry.scans_fused = built.scans_fused
    # the next batch takes a version above every stored one, replayed or skipped
    entry.committed = max([entry.version, *(version for version, _ in stored.batches)])
    return entry


class MapService:
    """Named maps in memory, backed by ``Storage``; fusion in threads, plans in processes."""

    def __init__(self, settings: Settings, storage: Storage, metrics: Metrics) -> None:
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        self._maps: dict[str, MapEntry] = {}
        self._quarantined: dict[str, str] = {}  # map name -> why it was set aside at start
        self._create_lock = asyncio.Lock()
        self._threads = ThreadPoolExecutor(settings.fusion_threads, thread_name_prefix="fusion")
        # parsing has its own threads: a burst of queued batches must not put its parsing ahead of
        # the commit and fusion of the batch whose turn it is, nor ahead of readers' copies
        self._parsers = ThreadPoolExecutor(settings.fusion_threads, thread_name_prefix="parse")
        # and reads too: a read of one map must not wait behind minutes of fusion of others (issue 11)
        self._readers = ThreadPoolExecutor(settings.read_threads, thread_name_prefix="read")
        self._committer = GroupCommitter(storage, metrics)
        self._plans = PlanPool(
            workers=settings.plan_workers, queue=settings.plan_queue, native=settings.native_planning,
            field_cache_bytes=settings.plan_cache_bytes,
        )
        # map versions published for the planner workers, so that a plan does not copy its map's grid
        self._reserve = DiskReserve(settings.data_dir, settings.disk_reserve_bytes)
        self._grids = PlanGrids(settings.data_dir / plangrids.DIRECTORY, settings.plan_cache_bytes, self._run,
                                metrics.plan_grid_bytes.set)
        self._limits = batches.Limits(max_scans=settings.max_scans_per_batch, max_rays=settings.max_rays_per_scan)
        self._kernels: asyncio.Task[None] | None = None
        self._kernels_error: str | None = None
        #: told of batches applied, plans made and maps deleted (``MapObserver``); None: nobody
        self.observer: MapObserver | None = None

    def _notify(self, event: str, *args: Any) -> None:
        """Tell the observer, if any; its failure is logged and goes no further (the change is done)."""
        if self.observer is not None:
            try:
                getattr(self.observer, event)(*args)
            except Exception:  # noqa: BLE001 - a viewer's bug must not fail a batch, a plan or a delete
                LOG.exception("map observer failed on %s", event)

    async def _run(self, fn: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._threads, fn, *args)

    async def _run_parser(self, fn: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._parsers, fn, *args)

    async def _run_read(self, fn: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._readers, fn, *args)

    # ---------------------------------------------------------------- lifecycle

    async def start(self) -> None:
        """Load every stored map (snapshot + replay) and, if configured, start the planner workers."""
        started = time.perf_counter()
        await self._run(self._grids.open)  # and remove what a killed run left
        await self._run(self._reserve.hold)
        # one map at a time: a start holds one map's snapshot and log, not every map's (issue 11: 377 MB
        # of log read at once peaked at 1.1 GB)
        replayed = 0
        for name in await self._run(self.storage.map_names):
            item = await self._run(self.storage.load_map, name)
            if item is None:  # cannot happen: nothing else writes before the start is done
                continue
            try:
                entry = await self._run(_restore, item)
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
        # in the background: /health answers meanwhile, /ready once they are done; a scan that comes first
        # waits for the kernel it needs (numba compiles one at a time), not for all of them
        self._kernels = asyncio.get_running_loop().create_task(self._warm_kernels())
        if self.settings.plan_warmup:
            self._plans.start()

    async def _warm_kernels(self) -> None:
        """Compile the fusion kernels, or load them from numba's cache, in a fusion thread, with progress in the log."""
        LOG.info("compiling the fusion kernels, or loading them from numba's cache (a first start compiles for "
                 "about 20 s)", extra={"fields": {"cache": os.environ.get("NUMBA_CACHE_DIR", "numba's default")}})

        def progress(step: str, seconds: float) -> None:
            LOG.info("kernels ready: %s", step, extra={"fields": {"seconds": round(seconds, 2)}})

        try:
            seconds = await self._run(warmup.warm_fusion, progress)
        except Exception as exc:  # noqa: BLE001 - a bug: readiness reports it; requests report their own
            self._kernels_error = f"the fusion kernels did not compile: {exc!r}"
            LOG.error(self._kernels_error, exc_info=True)
            return
        LOG.info("fusion kernels ready", extra={"fields": {"seconds": round(seconds, 2)}})

    def readiness(self) -> Readiness:
        """Ready for traffic: maps loaded (always, once the service answers), fusion kernels compiled or loaded,
        and the planner workers up and warmed (when FUZZYRISK_PLAN_WARMUP starts them with the service)."""
        kernels = self._kernels is not None and self._kernels.done() and self._kernels_error is None
        planners = self._plans.warm_state
        problems = [p for p in (self._kernels_error, self._plans.warm_error) if p]
        if problems:
            status = "failed"
        elif kernels and planners in ("off", "ready"):
            status = "ready"
        else:
            status = "starting"
        return Readiness(
            status=status, maps_loaded=len(self._maps), maps_quarantined=sorted(self._quarantined),
            kernels_compiled=kernels,
            planner_workers_ready=len(self._plans.warmed),
            planner_workers_wanted=self.settings.plan_workers if self.settings.plan_warmup else 0,
            detail="; ".join(problems),
        )

    async def stop(self) -> None:
        """Wait for batches in flight, snapshot every map with unsnapshotted batches, release everything."""
        for entry in list(self._maps.values()):
            ticket = entry.line.take()
            try:
                await entry.line.wait_all(ticket)
                if not entry.deleted and entry.version > entry.snapshot_version:
                    await self._snapshot(entry)
            finally:
                entry.line.done(ticket)
        if self._kernels is not None:
            self._kernels.cancel()  # a compilation under way still ends in its thread (below)
        self._committer.shutdown()
        self._plans.shutdown()
        self._parsers.shutdown(wait=True)
        self._readers.shutdown(wait=True)
        self._threads.shutdown(wait=True)  # grids being written included
        self._grids.close()
        self.storage.close()

    async def _snapshot(self, entry: MapEntry) -> None:
        """Store the map's arrays and drop the batches they cover; a failure is logged and counted only.

        The caller holds the map's apply turn (no batch can change the map meanwhile). Nothing is lost
        when this fails: the batches since the last snapshot stay in the log and are replayed at start.
        """
        async with entry.apply_lock:  # readers wait for the copy only, not for deflate and fsync
            version = entry.version
            arrays = await self._run(entry.map.to_arrays)
        try:
            await self._run(lambda: self.storage.write_snapshot(entry.name, version, _npz(arrays)))
        except Exception as exc:
            # StorageUnavailable (full, read-only) mostly, but whatever it is, the batch that triggered
            # the snapshot is committed and applied: it must still be acknowledged
            entry.snapshot_failed_version = version
            self.metrics.snapshot_failures.inc()
            LOG.warning(
                "snapshot failed; the batches stay in the log and the snapshot is retried later",
                extra={"fields": {"map": entry.name, "version": version, "error": str(exc)}},
            )
            return
        entry.snapshot_version = version
        while entry.log and entry.log[0][0] <= version:  # dropped from the log with the snapshot
            entry.log.popleft()
        self.metrics.snapshots.inc()

    def _snapshot_due(self, entry: MapEntry) -> bool:
        """Every ``FUZZYRISK_SNAPSHOT_EVERY`` batches, or once the log holds ``FUZZYRISK_SNAPSHOT_LOG_BYTES``.

        The bytes bound the disk a map takes (its snapshot, plus at most that much log and a batch):
        200 batches of 64 MiB would otherwise be 12.5 GiB of log for one map (issue 11).
        """
        every = self.settings.snapshot_every
        # after a failure, wait another ``every`` batches: a full disk should not cost a snapshot per batch
        if entry.snapshot_failed_version > entry.snapshot_version and entry.version - entry.snapshot_failed_version < every:
            return False
        logged = sum(size for version, size in entry.log if version <= entry.version)
        return entry.version - entry.snapshot_version >= every or logged >= self.settings.snapshot_log_bytes

    # ---------------------------------------------------------------- maps

    def _entry(self, name: str) -> MapEntry:
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
        return self._entry(name).info()

    def map_uid(self, name: str) -> int:
        """Tells the map now named ``name`` apart from an earlier or later map of that name (``MapEntry.uid``)."""
        return self._entry(name).uid

    @property
    def limits(self) -> batches.Limits:
        """The scans of one batch and the rays of one scan the service takes (``FUZZYRISK_MAX_SCANS_PER_BATCH``,
        ``FUZZYRISK_MAX_RAYS_PER_SCAN``)."""
        return self._limits

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
            now = _now()
            meta = {
                "name": request.name,
                "origin": list(request.origin),
                "size": list(request.size),
                "resolution": request.resolution,
                "model": request.model,
                "sensor": request.sensor.model_dump(),
                "frame_id": request.frame_id,
                "created": now,
            }
            if request.model == "fuzzy":
                meta["engine"] = engines.to_meta(request.engine or engines.default())
            self._check_room(meta)  # before the map's memory is taken
            try:
                built = await self._run(lambda: _build_map(meta, max_cells=self.settings.max_map_cells))
            except ValueError as exc:  # the grid was checked by _check_room: the sensor or the engine
                raise Invalid(str(exc)) from None
            try:
                await self._run(self.storage.create_map, request.name, meta, now)
            except NameTaken:
                raise Conflict(f"a map named {request.name!r} exists") from None
            entry = MapEntry(meta, built, 0, 0, 0, now)
            self._maps[request.name] = entry
            self.metrics.maps.set(len(self._maps))
            return entry.info()

    async def delete_map(self, name: str) -> None:
        """Remove a map and its stored rows (after the batches that arrived before, if any).

        A quarantined map (damaged rows, found at start) is dropped with its rows.
        """
        if name in self._quarantined and name not in self._maps:
            await self._run(self._delete_rows, name)
            del self._quarantined[name]
            return
        entry = self._entry(name)
        ticket = entry.line.take()
        # shielded as a batch's write is: a cancelled request must not leave the rows deleted
        # and the map still served
        await _shielded(self._delete(entry, ticket))

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
            await self._run(self._delete_rows, entry.name)
            entry.deleted = True
            del self._maps[entry.name]
            self._grids.retire(entry.uid)  # its files go now, or when the last plan on them ends
            self._notify("map_deleted", entry.name)
        finally:
            entry.line.done(ticket)
        self.metrics.maps.set(len(self._maps))

    # ---------------------------------------------------------------- scans

    def _parse(self, body: bytes, content_type: str, query: Mapping[str, str], dims: int) -> list[batches.Scan]:
        # the query first, as FastAPI checks query parameters before the route reads a body
        try:
            params = ScanQuery.model_validate(dict(query)).model_dump()
        except ValidationError as exc:
            errors = [{**e, "loc": ("query", *e["loc"])} for e in exc.errors(include_url=False)]
            raise RequestValidationError(errors) from None
        media = content_type.split(";")[0].strip().lower()
        if media in batches.BINARY_TYPES:
            return batches.from_binary(body, params, dims, self._limits)
        if media in rosmsgs.MEDIA_TYPES:  # a CDR-serialized LaserScan or PointCloud2, the pose in the query
            return rosmsgs.from_cdr(body, media, params, dims, self._limits)
        if media != "application/json":
            # none at all is refused too: a web page can send a body without one, and without a
            # CORS preflight (issue 11: a browser's no-cors fetch injected scans)
            given = f"Content-Type {media!r} is not accepted" if media else "a scan upload needs a Content-Type"
            raise UnsupportedMediaType(
                f"{given}: send application/json, or a binary scan as {' or '.join(batches.BINARY_TYPES)}, "
                f"or a ROS 2 message as {' or '.join(map(rosmsgs.media_type, rosmsgs.MSGTYPES))}"
            )
        try:
            batch = ScanBatch.model_validate_json(body)
        except ValidationError as exc:
            errors = [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False)]
            raise RequestValidationError(errors) from None
        return batches.from_json(batch, dims, self._limits)

    def _prepare(
        self, entry: MapEntry, body: bytes, content_type: str, query: Mapping[str, str]
    ) -> tuple[list[batches.Scan], bytes]:
        """Parse, validate (query and body) and encode a batch (no lock held: it touches no map state).

        In a parsing thread, or on the event loop for a small body (``INLINE_PARSE_BYTES``).
        """
        scans = self._parse(body, content_type, query, entry.spec.ndim)
        self._check_work(entry, scans)
        return scans, batches.encode(scans)

    def _check_work(self, entry: MapEntry, scans: list[batches.Scan]) -> None:
        """413 for a batch whose rays would walk more than ``FUZZYRISK_MAX_BATCH_CELLS`` cells of this map.

        Before it is stored: one small request (12 scans of 16,384 beams reaching past a 16 M-cell
        map's edges) would otherwise hold a fusion thread for a minute, and every restart replays it.
        """
        work = cast_work(entry.spec, scans)
        if work > self.settings.max_batch_cells:
            raise TooLarge(
                f"the batch's rays walk about {work:,} cells of this map, more than FUZZYRISK_MAX_BATCH_CELLS "
                f"({self.settings.max_batch_cells:,}): send fewer scans per batch, or shorter range_max"
            )

    def _apply(self, entry: MapEntry, version: int, scans: list[batches.Scan]) -> BatchResult:
        """Fuse a committed batch (in a fusion thread; the caller holds the apply turn and the apply lock)."""
        started = time.perf_counter()
        try:
            stats = entry.map.integrate_batch(scans)
        except BaseException:
            # never acknowledged: it must not come back at the next start
            try:
                self.storage.discard_batch(entry.name, version)
            except StorageUnavailable:
                LOG.exception("map %s: batch %d failed to apply and could not be removed from the log; "
                              "a start before the next snapshot will replay it", entry.name, version)
            self._rebuild(entry)
            raise
        model = entry.meta["model"]
        self.metrics.fusion_seconds.labels(model).observe(time.perf_counter() - started)
        self.metrics.scans_fused.labels(model).inc(stats.scans)
        self.metrics.rays.labels(model).inc(stats.rays)
        self.metrics.cells_updated.labels(model).inc(stats.cells_updated)
        return BatchResult(scans_fused=stats.scans, rays=stats.rays, cells_updated=stats.cells_updated, version=version)

    def _rebuild(self, entry: MapEntry) -> None:
        """Put back the map a failed batch may have changed in part: all or nothing (issue 11).

        The map is rebuilt from the store up to its current version, as a restart would rebuild
        it; should that fail too, the map is left as it is and the failure logged.
        """
        try:
            stored = self.storage.load_map(entry.name)
            if stored is None:
                return  # deleted meanwhile
            entry.map = _restore(stored, up_to=entry.version).map
        except Exception:  # noqa: BLE001 - the batch's own failure is the one the client gets
            LOG.exception("map %s: could not rebuild the map after a failed batch; it may differ from what a "
                          "restart rebuilds until then", entry.name)

    @contextlib.contextmanager
    def receiving(self, name: str) -> Iterator[None]:
        """Admit an upload (503, ``Retry-After`` when its map's line is full) and count it against the line while
        its body arrives; ``add_scans`` checks the line again as the batch joins it.

        Uploads read side by side would all pass a check that counts only the batches already in
        line: 40 bodies of 60 MB for one map were all read at once (issue 11). Counted from the
        first byte, one map's uploads hold at most ``FUZZYRISK_MAX_PENDING_BATCHES`` bodies, the
        others' share of the bodies-in-flight budget stays theirs.
        """
        entry = self._entry(name)
        self._admit(entry)
        entry.arriving += 1
        try:
            yield
        finally:
            entry.arriving -= 1

    def _admit(self, entry: MapEntry) -> None:
        waiting = entry.line.outstanding + entry.arriving
        if waiting >= self.settings.max_pending_batches:
            self.metrics.batches_rejected.labels("Backlog").inc()
            raise Unavailable(
                f"map {entry.name!r} already has {waiting} batches in line or arriving; slow down and retry "
                "(FUZZYRISK_MAX_PENDING_BATCHES)",
                headers={"Retry-After": "1"},
            )

    async def add_scans(
        self, name: str, *, body: bytes, content_type: str, query: Mapping[str, str]
    ) -> BatchResult:
        """Fuse one batch (JSON ``ScanBatch`` or one binary scan) into a map, durably, all or nothing.

        Batches to one map are committed and applied in the order they arrived here.
        """
        entry = self._entry(name)
        # no await between the check and the take: together they are atomic on the event loop
        self._admit(entry)
        ticket = entry.line.take()  # before any await: this fixes the batch's place in line
        try:
            if len(body) <= INLINE_PARSE_BYTES:
                scans, payload = self._prepare(entry, body, content_type, query)
            else:
                scans, payload = await self._run_parser(self._prepare, entry, body, content_type, query)
        except BaseException as exc:
            entry.line.done(ticket)
            if isinstance(exc, (Invalid, TooLarge, RequestValidationError, UnsupportedMediaType)):
                self.metrics.batches_rejected.labels(type(exc).__name__).inc()
            raise
        # the task owns the ticket from here; shielded, so that a cancelled request cannot leave its
        # batch committed but not applied
        return await _shielded(self._write(entry, ticket, scans, payload))

    async def add_parsed_scans(self, name: str, scans: list[batches.Scan], *, uid: int,
                               admitted: bool = False) -> BatchResult:
        """Fuse one batch of scans validated by the caller for map ``name`` (a bag upload's), as ``add_scans`` does.

        ``uid`` is the ``map_uid`` the scans were validated for: a map deleted and created again
        under the same name since (another grid, maybe another dimension) answers ``Conflict`` and
        stores nothing. ``admitted``: the batch belongs to an import whose first batch was admitted,
        so it is not refused for the line's length (an import is refused whole, or not at all).
        """
        entry = self._entry(name)
        if not admitted:
            self._admit(entry)
        ticket = entry.line.take()
        if entry.uid != uid:  # no await since the entry was looked up: the map holding the name now
            entry.line.done(ticket)
            raise Conflict(f"map {name!r} was deleted and created again while its scans were being read; "
                           "nothing was stored: import into the new map again")
        try:
            payload = await self._run_parser(self._checked_payload, entry, scans)
        except BaseException:
            entry.line.done(ticket)
            raise
        return await _shielded(self._write(entry, ticket, scans, payload))

    def _checked_payload(self, entry: MapEntry, scans: list[batches.Scan]) -> bytes:
        self._check_work(entry, scans)
        return batches.encode(scans)

    async def _write(self, entry: MapEntry, ticket: int, scans: list[batches.Scan], payload: bytes) -> BatchResult:
        """Commit, then apply, a parsed batch in its turns; gives both turns up when done, whatever happens."""
        try:
            await entry.line.commit.wait(ticket)
            if entry.deleted:
                raise NotFound(f"no map named {entry.name!r}")
            version, updated = entry.committed + 1, _now()
            # StorageUnavailable here leaves the map untouched: nothing is applied before the commit
            await asyncio.wrap_future(self._committer.append(BatchRecord(entry.name, version, payload, updated)))
            entry.committed = version
            entry.log.append((version, len(payload)))
            entry.line.commit.done(ticket)  # the next batch may commit while this one waits for its fusion
            await entry.line.apply.wait(ticket)
            async with entry.apply_lock:
                # a batch that fails here keeps its version taken (the map's version skips it): a
                # later batch may have committed with the next one meanwhile, and should its
                # removal from the log have failed too, the row is still there under this version
                try:
                    result = await self._run(self._apply, entry, version, scans)
                except BaseException:
                    # the map may have changed in part (issue 11): a grid published for its
                    # current version would no longer be that map
                    self._grids.retire(entry.uid)
                    raise
                # assigned here, on the event loop and under the apply lock, so that a reader and
                # MapInfo never pair the new arrays with the old version (or mix two versions)
                entry.version, entry.scans_fused, entry.updated = result.version, entry.map.scans_fused, updated
                entry.last_scan, entry.last_view = scans[-1], None
                self._grids.retire(entry.uid, below=entry.version)  # no plan will ask for an older one
                self._notify("batch_applied", entry.name, entry.version, entry.last_scan, entry.frame_id)
            if self._snapshot_due(entry):
                await self._snapshot(entry)
            return result
        finally:
            entry.line.done(ticket)

    async def last_scan(self, name: str) -> LastScan:
        """Beam ends of the last scan fused; the view is built at the first request, not per batch."""
        entry = self._entry(name)
        scan, view, version = entry.last_scan, entry.last_view, entry.version
        if scan is None:
            raise NotFound(f"map {name!r} has fused no scan since the service started")
        if view is None:
            # most batches are never drawn; a big cloud's view takes a while, so off the event loop
            view = await self._run_read(batches.scan_view, scan)
            if entry.last_scan is scan:  # not replaced by a newer batch meanwhile
                entry.last_view = view
        return LastScan(origin=view.origin, endpoints=view.endpoints, hit=view.hit, version=version)

    # ---------------------------------------------------------------- risk

    def current_etag(self, name: str, variant: Mapping[str, Any]) -> tuple[str, int]:
        """The ETag a read of ``variant`` would carry now, and the version (no grid read: for If-None-Match)."""
        entry = self._entry(name)
        return conditional.entity_tag(entry.etag_seed, entry.version, variant), entry.version

    async def read_grid(self, name: str) -> GridSnapshot:
        """The map's risk and observed arrays, consistent with one version.

        ``risk()`` and ``observed()`` already hand out new read-only arrays, so no copy is needed.
        """
        return await self._read_grid(self._entry(name))

    async def _read_grid(self, entry: MapEntry) -> GridSnapshot:
        async with entry.apply_lock:
            risk, observed = await self._run_read(lambda: (entry.map.risk(), entry.map.observed()))
            # version and updated are assigned together under this lock (``_write``): they match the arrays
            return GridSnapshot(entry.spec, entry.version, risk, observed, entry.frame_id, entry.updated,
                                entry.etag_seed)

    async def render_log(self, name: str, render: Callable[[GridSnapshot, StoredMap], T]) -> T:
        """``render(grid, stored)`` in a read thread: the map's grid and its stored batch log at one version.

        The grid is copied and the log read (``Storage.load_map``: the latest snapshot's version and the
        batches after it) together under the apply lock, so no batch is applied between the two: the log
        holds every batch up to the grid's version (each was committed before it was applied), and those
        committed but not applied yet are left out. ``render`` runs once the lock is released
        (``app.recording``); ``stored.snapshot`` is dropped, the arrays are not needed.
        """
        entry = self._entry(name)
        async with entry.apply_lock:
            risk, observed, stored = await self._run_read(
                lambda: (entry.map.risk(), entry.map.observed(), self.storage.load_map(entry.name)))
            grid = GridSnapshot(entry.spec, entry.version, risk, observed, entry.frame_id, entry.updated,
                                entry.etag_seed)
        if stored is None or stored.meta.get("created") != entry.meta["created"]:  # deleted (and made again)
            raise NotFound(f"no map named {name!r}; GET /maps lists them")
        if stored.damage:
            raise Unavailable(f"map {name!r}: its stored log is damaged ({'; '.join(stored.damage)})")
        stored.snapshot = None
        stored.batches = [(version, payload) for version, payload in stored.batches if version <= grid.version]
        return await self._run_read(render, grid, stored)

    async def risk_at(self, name: str, points: list[list[float]]) -> RiskValues:
        if len(points) > self.settings.max_query_points:
            raise TooLarge(
                f"{len(points)} points, more than the limit of {self.settings.max_query_points} "
                "(FUZZYRISK_MAX_QUERY_POINTS): split the query"
            )
        entry = self._entry(name)
        dims = entry.spec.ndim
        if any(len(p) != dims for p in points):
            bad = next(i for i, p in enumerate(points) if len(p) != dims)
            raise Invalid(f"points[{bad}] has {len(points[bad])} coordinates; this map is {dims}-D")
        async with entry.apply_lock:
            try:
                values = await self._run_read(entry.map.risk_at, np.asarray(points, dtype=np.float64))
            except ValueError as exc:
                raise Invalid(str(exc)) from None
            return RiskValues(risk=[float(v) for v in values], version=entry.version)

    async def risk_json(self, name: str) -> tuple[bytes, GridSnapshot]:
        """The grid as ``RiskGridJSON``, serialised (off the event loop: big maps make big documents)."""
        grid = await self.read_grid(name)
        if grid.spec.num_cells > MAX_JSON_CELLS:
            raise Invalid(
                f"the map has {grid.spec.num_cells} cells, too many for JSON (at most {MAX_JSON_CELLS}); "
                "ask for format=npy or format=png"
            )

        def encode() -> bytes:
            return RiskGridJSON(
                name=name, version=grid.version, frame_id=grid.frame_id, resolution=grid.spec.resolution,
                origin=list(grid.spec.origin), shape=list(grid.spec.shape),
                risk=np.round(grid.risk.astype(np.float64), 6).tolist(), observed=grid.observed.tolist(),
            ).model_dump_json().encode()

        return await self._run_read(encode), grid

    async def risk_npy(self, name: str, layer: Literal["risk", "observed"] = "risk") -> tuple[bytes, GridSnapshot]:
        """The risk (float32) or the observed mask (bool) as ``.npy``, of one version."""
        grid = await self.read_grid(name)
        return await self._run_read(exports.npy_bytes, grid.risk if layer == "risk" else grid.observed), grid

    async def risk_png(self, name: str, *, scale: int, z_min: float | None, z_max: float | None) -> tuple[bytes, GridSnapshot]:
        _check_band(z_min, z_max)
        grid = await self.read_grid(name)
        nx, ny = grid.spec.shape[:2]
        if nx * ny * scale * scale > MAX_PNG_PIXELS:
            raise Invalid(f"scale {scale} would make a {nx * scale} x {ny * scale} image; use a smaller scale")
        text = {
            "map": name, "version": str(grid.version), "frame_id": grid.frame_id,
            "resolution": repr(grid.spec.resolution), "origin": repr(list(grid.spec.origin)),
        }

        def render() -> bytes:
            risk, observed = grid.planar(z_min, z_max)
            return exports.risk_png(risk, observed, scale=scale, text=text)

        return await self._run_read(render), grid

    async def nav2_zip(
        self, name: str, *, mode: Literal["trinary", "scale", "raw"], image_format: Literal["pgm", "png"],
        free_thresh: float, occupied_thresh: float, z_min: float | None, z_max: float | None,
    ) -> tuple[bytes, GridSnapshot]:
        """The zip for map_server; its entries are dated by the map's last batch, so one version gives one file."""
        _check_band(z_min, z_max)
        _check_thresholds(free_thresh, occupied_thresh)
        try:
            exports.check_nav2_format(mode, image_format)
        except ValueError as exc:
            raise Invalid(str(exc)) from None
        grid = await self.read_grid(name)

        def render() -> bytes:
            risk, observed = grid.planar(z_min, z_max)
            return exports.nav2_zip(
                risk, observed, resolution=grid.spec.resolution, origin_xy=grid.spec.origin[:2], mode=mode,
                image_format=image_format, free_thresh=free_thresh, occupied_thresh=occupied_thresh,
                frame_id=grid.frame_id, date_time=rosout.zip_date_time(grid.updated),
            )

        return await self._run_read(render), grid

    async def occupancy_grid(
        self, name: str, *, mode: Literal["trinary", "scale", "probability"], free_thresh: float,
        occupied_thresh: float, z_min: float | None, z_max: float | None,
        encoding: Literal["json", "cdr", "mcap"] = "json",
    ) -> tuple[bytes, GridSnapshot]:
        """The map as a ``nav_msgs/OccupancyGrid``: JSON (``OccupancyGrid``), CDR bytes, or an MCAP file.

        The stamp and ``map_load_time`` are when the map reached this version (``GridSnapshot.updated``),
        so every read of one version gives the same bytes.
        """
        _check_band(z_min, z_max)
        _check_thresholds(free_thresh, occupied_thresh)
        grid = await self.read_grid(name)

        def render() -> bytes:
            risk, observed = grid.planar(z_min, z_max)
            data = exports.occupancy_data(risk, observed, mode=mode, free_thresh=free_thresh,
                                          occupied_thresh=occupied_thresh)
            stamp = rostypes.ros_time_of_iso(grid.updated)
            if encoding != "json":
                message = rosout.occupancy_grid_message(
                    data, width=risk.shape[0], height=risk.shape[1], resolution=grid.spec.resolution,
                    origin_xy=grid.spec.origin[:2], frame_id=grid.frame_id, stamp=stamp,
                )
                cdr = rosout.occupancy_grid_cdr(message)
                if encoding == "cdr":
                    return cdr
                return rosout.occupancy_grid_mcap(cdr, log_time_ns=rostypes.ns_of_ros_time(stamp))
            # the small fields through the model (validated), the 4-16 M values by numpy: one pydantic pass over
            # them held the GIL, and so every request, for seconds (issue 11)
            head = OccupancyGrid.model_validate({
                "header": {"stamp": stamp, "frame_id": grid.frame_id},
                "info": {
                    "map_load_time": stamp, "resolution": grid.spec.resolution,
                    "width": int(risk.shape[0]), "height": int(risk.shape[1]),
                    "origin": {"position": {"x": grid.spec.origin[0], "y": grid.spec.origin[1], "z": 0.0},
                               "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                },
                "data": [],
                "version": grid.version,
            }).model_dump_json().encode()
            empty = b'"data":[]'
            assert head.count(empty) == 1
            return head.replace(empty, b'"data":' + exports.int8_json_array(data))

        return await self._run_read(render), grid

    # ---------------------------------------------------------------- plans

    async def plan(self, name: str, request: PlanRequest) -> PlanResult:
        """Plan on the map's current risk in a worker process (``planning.plan`` checks the parameters).

        The worker gets the map version's published grid (``app.plangrids``), written by the first plan
        on that version; or, when it cannot be published, the arrays themselves.
        """
        self._check_plan(request)
        started = time.perf_counter()  # the wait for the grid is part of what the client waits for
        # the path's stamp: when the plan was taken up, as Nav2's planners stamp a path when they start it
        stamp = rostypes.ros_time_of_ns(time.time_ns())
        entry = self._entry(name)
        # goal_yaw only orients the answer's last pose: the planner never sees it
        params = request.model_dump(exclude_none=True, exclude={"goal_yaw"})
        timeout = wall_clock_limit(request.time_limit, request.seed is not None) + PLAN_GRACE_S
        outcome, source, version = "error", "shared", entry.version
        lease: Lease | None = self._grids.lease(entry.uid, version)  # no await since the version was read
        grid: GridSnapshot | None = None
        try:
            if lease is None:
                grid = await self._read_grid(entry)
                source, version = "published", grid.version
                lease = await self._grids.publish(
                    entry.uid, grid.version, grid.risk, grid.observed, grid.spec.resolution, grid.spec.origin,
                    current=functools.partial(_is_current, entry, grid.version),
                )
            self.metrics.plan_grids.labels("shipped" if lease is None else source).inc()
            if lease is not None:
                answer = await self._plans.run(run_shared_plan, timeout, lease.ref, params, key=name)
            else:
                assert grid is not None
                answer = await self._plans.run(
                    run_plan, timeout, grid.risk, grid.observed, grid.spec.resolution, grid.spec.origin, params,
                    key=name,
                )
            if "error" in answer:
                outcome = "rejected"
                raise PlanRejected(answer["error"]["code"], answer["error"]["message"])
            if "invalid" in answer:
                outcome = "invalid"
                raise Invalid(answer["invalid"])
            result = answer["result"]
            outcome = result["status"]
            path_msg = rosout.path_message(result["path"], state_space=result["state_space"], frame_id=entry.frame_id,
                                           stamp=stamp, goal_yaw=request.goal_yaw)
            plan = PlanResult(**result, version=version, **path_msg)
            self._notify("plan_made", name, plan, entry.frame_id)
            return plan
        finally:
            if lease is not None:
                lease.release()
            self.metrics.plan_seconds.labels(request.planner, outcome).observe(time.perf_counter() - started)

    def _check_plan(self, request: PlanRequest) -> None:
        """What can be refused without a worker: the service's time limit, and an unknown planner."""
        if request.time_limit > self.settings.max_plan_time_s:
            raise Invalid(
                f"time_limit {request.time_limit} s is above the limit of {self.settings.max_plan_time_s} s "
                "(FUZZYRISK_MAX_PLAN_TIME_S)"
            )
        try:
            planner_spec(request.planner)  # lists the planners that work
        except ValueError as exc:
            raise Invalid(str(exc)) from None
        if request.goal_yaw is not None and request.state_space in rosout.YAW_SPACES:
            raise Invalid(f"goal_yaw is for R2 and R3 paths; in {request.state_space} give the goal's yaw as its "
                          "third value [x, y, theta] and leave goal_yaw out")


def _is_current(entry: MapEntry, version: int) -> bool:
    """Is ``version`` still the version of the map that ``entry`` holds?"""
    return not entry.deleted and entry.version == version


async def _shielded(work: Coroutine[Any, Any, T]) -> T:
    """Run ``work`` to its end even if the awaiting request is cancelled (a client gone away)."""
    task = asyncio.ensure_future(work)
    task.add_done_callback(_retrieve)
    return await asyncio.shield(task)


def _retrieve(task: asyncio.Future[Any]) -> None:
    """Mark a shielded task's exception as seen: its request may have been cancelled, and the error
    reached the client (or nobody) through the shield, not through this task."""
    if not task.cancelled():
        task.exception()


def _check_thresholds(free_thresh: float, occupied_thresh: float) -> None:
    # an 8-bit map image needs a grey strictly between the thresholds for "unknown"
    try:
        exports.check_thresholds(free_thresh, occupied_thresh)
    except ValueError as exc:
        raise Invalid(str(exc)) from None


def _check_band(z_min: float | None, z_max: float | None) -> None:
    if z_min is not None and z_max is not None and z_min > z_max:
        raise Invalid(f"z_min ({z_min}) must not exceed z_max ({z_max})")
