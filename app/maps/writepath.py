"""The write path: a map's batches in arrival order, committed, applied, snapshotted.

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
  applied, while a snapshot copies the arrays and while a reader (risk, query, plan)
  copies. A batch of scans is cast in its apply turn before it takes the lock (the
  cast reads the map's blocks and changes nothing: ``FuzzyMap.prepare_batch``), so
  readers wait for its fusion, not its ray casting. A due snapshot copies the map in its batch's apply turn, then is deflated
  and stored beside the line (``MapEntry.snapshotting``, in the admin thread): the
  batch is acknowledged without waiting for the write. Delete and the final
  snapshot wait for it.
  A reader waits for at most the batch being applied, never behind the queued ones,
  and never sees a half-applied batch or a version that does not match the arrays.

The CPU work runs off the event loop: parsing and validation of big bodies in
parsing threads (JSON ones above 256 KiB in a parse process, ``app.maps.ingest_process``), fusion in the fusion threads (numpy and numba release the GIL), commits in one
writer thread (``app.storage.committer``: batches queued meanwhile, from any map, share a
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
import logging
import math
import time
import traceback
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping

import numpy as np
from fastapi.exceptions import RequestValidationError

from app.formats.saved_maps import MapCells
from app.maps import logcodec, snapshotcodec
from app.maps.logcodec import Batch, Edit, Prior, SetForget
from app.scans import Limits, Scan
from app.maps import ingest
from app.storage.committer import GroupCommitter
from app.config import Settings
from app.errors import (
    Conflict,
    InsufficientStorage,
    Invalid,
    NotFound,
    TooLarge,
    Unavailable,
    UnsupportedMediaType,
)
from app.maps.entry import MapEntry, now
from app.maps.history import plan_fold
from app.maps.line import shielded
from app.maps.stored import batch_work, integrate, replay, restore
from app.ops.metrics import Metrics
from app.maps.ingest_process import ParseProcess, wants
from app.maps.shared_grids import PlanGrids
from app.maps.registry import MapRegistry
from app.schemas import BatchResult
from app.storage import BatchRecord, MapGone, Storage, StorageUnavailable
from app.ops.threads import Workers
from fuzzyocc import FuzzyMap, LaserScan
from fuzzyocc.config import MAX_COORDINATE_M
from fuzzyocc.maps import PreparedBatch

LOG = logging.getLogger("fuzzyrisk.maps")

#: Bodies up to this size are parsed on the event loop rather than in a parsing thread: their parse
#: (pydantic holds the GIL either way, so the loop waits for it wherever it runs) takes well under a
#: millisecond, less than the two thread switches of a trip through the parsing pool.
INLINE_PARSE_BYTES = 128 * 1024
#: A batch whose rays walk more cells than this (about 2 s of a thread: the walks go at 40-60 M cells a second) is
#: heavy: it is fused in threads of its own, so that heavy batches never hold every fusion thread (a robot's batch
#: of a few 1080-beam scans walks about 1 M cells, a 128-beam lidar's sweep at 0.1 m about 23 M: a lidar's map is
#: not heavy, its sweeps are its robot's stream).
HEAVY_BATCH_CELLS = 100_000_000
#: A batch whose rays walk more cells than this is cast in its apply turn before it takes the apply lock (readers wait
#: for its fusion alone: an Ouster sweep at 0.1 m walks 23 M); a lighter one is cast and fused in one hop to a fusion
#: thread, as its cast takes a few milliseconds and a second hop, under load, cost the other maps' scans more than it
#: saved its readers.
CAST_AHEAD_CELLS = 2_000_000


class WritePath:
    """Batches into maps: admitted, parsed, committed (group commit), applied in order; snapshots when due."""

    def __init__(self, settings: Settings, storage: Storage, metrics: Metrics, workers: Workers,
                 registry: MapRegistry, grids: PlanGrids, notify: Callable[..., None]) -> None:
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        self._workers = workers
        self._registry = registry
        self._grids = grids
        self._notify = notify
        self._committer = GroupCommitter(storage, metrics)
        self._limits = Limits(max_scans=settings.max_scans_per_batch, max_rays=settings.max_rays_per_scan)
        #: large JSON bodies are parsed in it: scan batches here, corrected trajectories by ``Refusions``
        self.parse_process = ParseProcess()
        #: snapshots taken beside the lines, also of maps no longer held (``stop`` waits for them all)
        self._snapshots: set[asyncio.Task[None]] = set()

    @property
    def limits(self) -> Limits:
        """The scans of one batch and the rays of one scan the service takes (``FUZZYRISK_MAX_SCANS_PER_BATCH``,
        ``FUZZYRISK_MAX_RAYS_PER_SCAN``)."""
        return self._limits

    @property
    def snapshots_being_written(self) -> int:
        """Snapshots copied and not yet stored (``_snapshot_beside``)."""
        return len(self._snapshots)

    async def stop(self) -> None:
        """Wait for the batches in flight, snapshot every map with unsnapshotted batches, stop the committer."""
        if self._snapshots:
            await asyncio.wait(list(self._snapshots))
        for entry in self._registry.held_maps:
            ticket = entry.line.take()
            try:
                await entry.line.wait_all(ticket)
                await entry.snapshot_done()
                if not entry.deleted and entry.version > entry.snapshot_version:
                    # a fold that re-fuses history would hold the stop: only the cheap one (the budget 0's)
                    await self._store_snapshot(entry, *await self._copy(entry), replay_fold=False)
            finally:
                entry.line.done(ticket)
        self._committer.shutdown()
        await asyncio.to_thread(self.parse_process.shutdown)

    async def _copy(self, entry: MapEntry) -> tuple[int, dict[str, np.ndarray]]:
        """The map's version and a copy of its arrays, taken under the apply lock: one version's map."""
        async with entry.apply_lock:  # batches and readers wait for the copy only, not for deflate and fsync
            return entry.version, await self._workers.run(entry.map.snapshot_arrays)

    async def _store_snapshot(self, entry: MapEntry, version: int, arrays: dict[str, np.ndarray], *,
                              replay_fold: bool) -> None:
        """Store the map's arrays as its restart snapshot, then fold its history if it is over the budget (``_fold``);
        a failure is logged and counted only.

        Nothing is lost when this fails: the batches since the last snapshot stay in the log and are
        replayed at start.
        """
        try:
            # in the admin thread: the fusion threads are for batches
            await self._workers.run_admin(
                lambda: self.storage.write_snapshot(entry.name, version, snapshotcodec.encode(arrays), entry.incarnation))
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
        entry.snapshot_version = max(entry.snapshot_version, version)
        # what a restart replays starts after the snapshot (later batches, and another replica's caught up, stay)
        entry.log = collections.deque(item for item in entry.log if item[0] > version)
        self.metrics.snapshots.inc()
        await self._fold(entry, replay=replay_fold)

    async def _fold(self, entry: MapEntry, *, replay: bool) -> None:
        """Fold the oldest batches of the map's history into its base when the history takes more than
        ``FUZZYRISK_MAX_HISTORY_BYTES`` (``history.plan_fold``), beside the map's line as its snapshot is.

        The history up to the fold is re-fused in a heavy fusion thread (niced: batches come first), the
        base stored with the batches' removal in the admin thread, in one transaction: a crash leaves the
        old history or the new one. A failure is logged and counted; the next snapshot tries again.
        """
        try:
            fold = await self._workers.run_heavy(functools.partial(
                plan_fold, self.storage, entry.name, entry.incarnation, budget=self.settings.max_history_bytes,
                replay=replay))
            if fold is None:
                return
            done = await self._workers.run_admin(
                self.storage.write_base, entry.name, fold.version, fold.payload, entry.incarnation, fold.planned_at)
        except Exception as exc:
            self.metrics.history_fold_failures.inc()
            LOG.warning("the history could not be folded; it stays as it is and the fold is tried again after the "
                        "next snapshot", extra={"fields": {"map": entry.name, "error": str(exc)}})
            return
        if done:  # (not when another replica folded first)
            self.metrics.history_folds.inc()
            LOG.info("history folded", extra={"fields": {"map": entry.name, "from_version": fold.version}})

    async def _snapshot_beside(self, entry: MapEntry) -> None:
        """Copy the map now, then deflate and store the copy without making anyone wait for it.

        The caller holds the map's apply turn, so the snapshot is of its batch's version. Waiting for the
        whole snapshot cost that batch's client the deflate and an fsync besides the copy (15-60 ms on a
        420 x 420 map, one scan in every ``FUZZYRISK_SNAPSHOT_EVERY``: a third of an innocent client's
        slowest scans in ``bench abuse``); the copy alone is 2-3 ms.
        """
        version, arrays = await self._copy(entry)
        task = asyncio.get_running_loop().create_task(self._store_snapshot(entry, version, arrays, replay_fold=True))
        entry.snapshotting = task
        self._snapshots.add(task)

        def forget(_: asyncio.Task[None]) -> None:
            entry.snapshotting = None
            self._snapshots.discard(task)

        task.add_done_callback(forget)

    def _snapshot_due(self, entry: MapEntry) -> bool:
        """Every ``FUZZYRISK_SNAPSHOT_EVERY`` batches, or once the log holds ``FUZZYRISK_SNAPSHOT_LOG_BYTES`` or
        walks ``FUZZYRISK_SNAPSHOT_LOG_CELLS``.

        The bytes bound the disk a map takes (its snapshot, plus at most that much log and a batch):
        200 batches of 64 MiB would otherwise be 12.5 GiB of log for one map. The cells bound
        the fusion a restart replays: 28 scans of 2 M beams (8 MB each, under the bytes) took 52-56 s.
        """
        if entry.snapshotting is not None:
            return False
        every = self.settings.snapshot_every
        # after a failure, wait another ``every`` batches: a full disk should not cost a snapshot per batch
        if entry.snapshot_failed_version > entry.snapshot_version and entry.version - entry.snapshot_failed_version < every:
            return False
        logged = walked = 0
        for version, size, cells in entry.log:
            if version <= entry.version:
                logged, walked = logged + size, walked + cells
        return (entry.version - entry.snapshot_version >= every or logged >= self.settings.snapshot_log_bytes
                or walked >= self.settings.snapshot_log_cells)


    def _prepare(
        self, entry: MapEntry, body: bytes, content_type: str, query: Mapping[str, str], received_ns: int
    ) -> tuple[list[Scan], bytes, int]:
        """Parse, validate (query and body), stamp and encode a batch, with its cast work (no lock held: it touches
        no map state). In a parsing thread, or on the event loop for a small body (``INLINE_PARSE_BYTES``).
        """
        return ingest.prepare(body, content_type, query, entry.spec.ndim, self._limits, entry.spec,
                              self._budget(entry), received_ns)

    @staticmethod
    async def _cast_ahead(entry: MapEntry, batch: Batch,
                          run: Callable[..., Awaitable[PreparedBatch | None]]) -> PreparedBatch | None:
        """A batch of scans cast in its apply turn before the apply lock is taken (the cast leaves the map as it is):
        readers then wait for its fusion alone (an Ouster sweep at 0.1 m: 0.3 of its 0.8 s on one core). None for
        anything else, or when the cast fails (the fusion, which casts again, then fails as the batch's failure)."""
        if not isinstance(batch, list) or not batch:
            return None
        try:
            return await run(entry.map.prepare_batch, batch)
        except Exception:  # noqa: BLE001 - whatever stops the cast stops the fusion too, where _apply handles it
            return None

    def _apply(self, entry: MapEntry, version: int, batch: Batch, prepared: PreparedBatch | None = None,
               cast_s: float = 0.0) -> BatchResult:
        """Fuse a committed batch (in a fusion thread; the caller holds the apply turn and the apply lock), cast
        ahead as ``prepared`` if it was, in ``cast_s`` seconds (counted in the fusion's time)."""
        started = time.perf_counter()
        try:
            stats = integrate(entry.map, batch, prepared)
        except BaseException as exc:
            # never acknowledged: it must not come back at the next start
            try:
                self.storage.discard_batch(entry.name, version, entry.incarnation)
            except StorageUnavailable:
                LOG.exception("map %s: batch %d failed to apply and could not be removed from the log; "
                              "a start before the next snapshot will replay it", entry.name, version)
            self._rebuild(entry)
            # the frames of the traceback hold the replaced map (``self`` of integrate_batch), and the error
            # and its frames make a cycle: that map, maybe hundreds of MB after a MemoryError, would stay until
            # the cyclic collector ran
            traceback.clear_frames(exc.__traceback__)
            raise
        model = entry.meta["model"]
        self.metrics.fusion_seconds.labels(model).observe(time.perf_counter() - started + cast_s)
        self.metrics.scans_fused.labels(model).inc(stats.scans)
        self.metrics.rays.labels(model).inc(stats.rays)
        self.metrics.cells_updated.labels(model).inc(stats.cells_updated)
        return BatchResult(scans_fused=stats.scans, rays=stats.rays, cells_updated=stats.cells_updated, version=version)

    def _rebuild(self, entry: MapEntry) -> None:
        """Put back the map a failed batch may have changed in part: all or nothing.

        The map is rebuilt from the store up to its current version, as a restart would rebuild
        it; should that fail too, the map is left as it is and the failure logged.
        """
        try:
            stored = self.storage.load_map(entry.name)
            if stored is None or stored.incarnation != entry.incarnation:
                return  # deleted (and made again) meanwhile: the next request drops this copy
            fresh = restore(stored, up_to=entry.version)
            entry.map = fresh.map
            if fresh.version > entry.version:
                # another replica's snapshot is newer than the version held: the map is now at that version
                entry.version, entry.updated, entry.scans_fused = fresh.version, fresh.updated, fresh.scans_fused
                entry.snapshot_version, entry.checked = fresh.snapshot_version, max(entry.checked, fresh.version)
        except Exception:
            LOG.exception("map %s: could not rebuild the map after a failed batch; it may differ from what a "
                          "restart rebuilds until then", entry.name)

    @contextlib.asynccontextmanager
    async def receiving(self, name: str) -> AsyncIterator[MapEntry]:
        """Admit an upload (503, ``Retry-After`` when its map's line is full) and count it against the line while
        its body arrives; ``add_scans`` checks the line again as the batch joins it.

        Uploads read side by side would all pass a check that counts only the batches already in
        line: 40 bodies of 60 MB for one map were all read at once. Counted from the
        first byte, one map's uploads hold at most ``FUZZYRISK_MAX_PENDING_BATCHES`` bodies, the
        others' share of the bodies-in-flight budget stays theirs. Yields the map as it is held now.
        """
        entry, _ = await self._registry.held(name)
        self._admit(entry)
        entry.arriving += 1
        try:
            yield entry
        finally:
            entry.arriving -= 1

    def _admit(self, entry: MapEntry) -> None:
        waiting = entry.batches_in_line
        if waiting >= self.settings.max_pending_batches:
            self.metrics.batches_rejected.labels("Backlog").inc()
            raise Unavailable(
                f"map {entry.name!r} already has {waiting} batches in line or arriving; slow down and retry "
                "(FUZZYRISK_MAX_PENDING_BATCHES)",
                headers={"Retry-After": "1"},
            )

    def _check_memory(self, entry: MapEntry) -> None:
        """507 for scans to a map that holds ``FUZZYRISK_MAX_MAP_CELLS`` cells, or when the maps together hold
        ``FUZZYRISK_MAX_TOTAL_CELLS`` (a clear, ``forget_beyond`` or a delete make room; an edit is never refused)."""
        held = entry.map.held_cells()
        if held >= self.settings.max_map_cells:
            raise InsufficientStorage(
                f"map {entry.name!r} holds {held:,} cells, its limit (FUZZYRISK_MAX_MAP_CELLS): clear a region "
                "(POST /maps/{name}/clear), set forget_beyond (PATCH /maps/{name}), or delete the map")
        total = self._registry.held_cells()
        if total >= self.settings.max_total_cells:
            raise InsufficientStorage(
                f"the maps hold {total:,} cells, the service's limit (FUZZYRISK_MAX_TOTAL_CELLS): clear regions, set "
                "forget_beyond, or delete maps")

    async def add_scans(
        self, name: str, *, body: bytes, content_type: str, query: Mapping[str, str]
    ) -> BatchResult:
        """Fuse one batch (JSON ``ScanBatch`` or one binary scan) into a map, durably, all or nothing.

        Batches to one map are committed and applied in the order they arrived here. A scan without a stamp of
        its own is stamped with the time the batch arrived here (the service's clock).
        """
        received_ns = time.time_ns()
        entry, _ = await self._registry.held(name)
        self._check_memory(entry)
        # no await between the check and the take: together they are atomic on the event loop
        self._admit(entry)
        ticket = entry.line.take()  # before any await: this fixes the batch's place in line
        try:
            if len(body) <= INLINE_PARSE_BYTES:
                scans, payload, work = self._prepare(entry, body, content_type, query, received_ns)
            elif wants(body, content_type):
                payload, work = await self.parse_process.prepare(
                    body, content_type, query, entry.spec.ndim, self._limits, entry.spec, self._budget(entry),
                    received_ns)
                scans = await self._workers.run_parser(logcodec.decode_scans, payload)  # 8 x 2 M ranges: 0.2 s
            else:
                scans, payload, work = await self._workers.run_parser(self._prepare, entry, body, content_type,
                                                                      query, received_ns)
        except BaseException as exc:
            entry.line.done(ticket)
            if isinstance(exc, (Invalid, TooLarge, RequestValidationError, UnsupportedMediaType)):
                self.metrics.batches_rejected.labels(type(exc).__name__).inc()
            raise
        # the task owns the ticket from here; shielded, so that a cancelled request cannot leave its
        # batch committed but not applied
        return await shielded(self._write(entry, ticket, scans, payload, work))

    async def add_parsed_scans(self, name: str, scans: list[Scan], *, uid: int,
                               admitted: bool = False) -> BatchResult:
        """Fuse one batch of scans validated by the caller for map ``name`` (a bag upload's), as ``add_scans`` does.

        ``uid`` is the ``map_uid`` the scans were validated for: a map deleted and created again
        under the same name since (another grid, maybe another dimension) answers ``Conflict`` and
        stores nothing. ``admitted``: the batch belongs to an import whose first batch was admitted,
        so it is not refused for the line's length (an import is refused whole, or not at all). Scans without a
        stamp are stamped as ``add_scans`` stamps them.
        """
        scans = ingest.stamped(scans, time.time_ns())
        entry, _ = await self._registry.held(name)
        self._check_memory(entry)
        if not admitted:
            self._admit(entry)
        ticket = entry.line.take()
        if entry.uid != uid:  # no await since the entry was looked up: the map holding the name now
            entry.line.done(ticket)
            raise Conflict(f"map {name!r} was deleted and created again while its scans were being read; "
                           "nothing was stored: import into the new map again")
        try:
            payload, work = await self._workers.run_parser(self._checked_payload, entry, scans)
        except BaseException:
            entry.line.done(ticket)
            raise
        return await shielded(self._write(entry, ticket, scans, payload, work))

    def _budget(self, entry: MapEntry) -> ingest.BatchBudget:
        """What a batch may cost this map (a bayes map holds its whole box: it takes on no cell)."""
        fuzzy = isinstance(entry.map, FuzzyMap)
        return ingest.BatchBudget(walk=self.settings.max_batch_cells,
                                  new_cells=self.settings.max_new_cells_per_batch if fuzzy else None)

    def _checked_payload(self, entry: MapEntry, scans: list[Scan]) -> tuple[bytes, int]:
        return ingest.checked_payload(entry.spec, scans, self._budget(entry))

    async def add_edit(self, name: str, edit: Edit) -> BatchResult:
        """Apply an edit of map ``name`` (a region cleared, ``forget_beyond`` changed) in the map's line, committed
        first as a batch is: durable before the answer, replayed in its place among the scans."""
        entry, _ = await self._registry.held(name)
        self._admit(entry)
        ticket = entry.line.take()
        try:
            _check_edit(entry, edit)
            payload = logcodec.encode_edit(edit)
        except BaseException:
            entry.line.done(ticket)
            raise
        return await shielded(self._write(entry, ticket, edit, payload, 0))

    async def add_prior(self, name: str, incarnation: str | None, cells: MapCells, weight: int) -> BatchResult:
        """Fuse a saved map's cells into map ``name`` as its first batch: each as if ``weight`` scans had agreed on
        it (``OccupancyMap.prior_levels``), committed and applied in the map's line as a scan batch is.

        Call it right after the map is created: with one process holding the maps, no await comes between the
        creation and the ticket taken here, so no other batch can come first. ``incarnation`` is the map's as
        created: a map deleted and created again meanwhile answers ``Conflict`` and stores nothing.
        """
        entry, _ = await self._registry.held(name)
        ticket = entry.line.take()
        if entry.incarnation != incarnation:
            entry.line.done(ticket)
            raise Conflict(f"map {name!r} was deleted and created again while it was being imported; nothing of the "
                           "import was stored")
        try:
            prior, payload, work = await self._workers.run_parser(self._prior_payload, entry, cells, weight)
        except BaseException:
            entry.line.done(ticket)
            raise
        return await shielded(self._write(entry, ticket, prior, payload, work))

    @staticmethod
    def _prior_payload(entry: MapEntry, cells: MapCells, weight: int) -> tuple[Prior, bytes, int]:
        # the map's levels come from a probe map of its kind: its own cells are not read (no apply lock needed)
        prior = Prior(levels=entry.map.prior_levels(cells.occupancy, weight)[cells.codes])
        return prior, logcodec.encode_prior(prior), batch_work(entry.spec, prior)

    async def _write(self, entry: MapEntry, ticket: int, batch: Batch, payload: bytes,
                     work: int) -> BatchResult:
        """Commit, then apply, a parsed batch in its turns; gives both turns up when done, whatever happens.

        A batch whose rays walk more than ``HEAVY_BATCH_CELLS`` is fused in the heavy batches' threads: two
        scans of 2 M beams held both fusion threads for 3-4 s, and every other map's batch (and the reads of
        that map, behind its apply lock) waited for them.
        """
        version = 0
        try:
            await entry.line.commit.wait(ticket)
            if entry.deleted:
                raise NotFound(f"no map named {entry.name!r}")
            updated = now()
            scans = batch if isinstance(batch, list) else []  # a prior or an edit fuses no scan
            stamps = [scan.stamp_ns for scan in scans if scan.stamp_ns is not None]
            record = BatchRecord(entry.name, entry.incarnation, payload, updated, len(scans),
                                 stamps[0] if stamps else None)
            try:
                # the store decides the version (with replicas, theirs and ours come in one order);
                # StorageUnavailable here leaves the map untouched: nothing is applied before the commit
                version = await asyncio.wrap_future(self._committer.append(record))
            except MapGone:
                raise await self._registry.gone(entry) from None
            entry.inflight.add(version)
            entry.log.append((version, len(payload), work))
            entry.line.commit.done(ticket)  # the next batch may commit while this one waits for its fusion
            await entry.line.apply.wait(ticket)
            run = self._workers.run_heavy if work > HEAVY_BATCH_CELLS else self._workers.run
            cast_started = time.perf_counter()
            prepared = await self._cast_ahead(entry, batch, run) if work > CAST_AHEAD_CELLS else None
            cast_s = time.perf_counter() - cast_started
            async with entry.apply_lock:
                if version > max(entry.version, entry.checked) + 1:
                    # other replicas' batches (or a discarded one) came between: theirs first, in the store's order
                    try:
                        await self._catch_up_locked(entry, version - 1)
                    except StorageUnavailable as exc:
                        raise Unavailable(
                            f"the batch is stored as version {version} of map {entry.name!r}, but the database could "
                            f"not be read to apply the batches before it ({exc}); it will be applied with them at the "
                            "map's next read: do not send it again", headers={"Retry-After": "1"}) from exc
                if version <= entry.version:
                    # caught up to another replica's snapshot that already holds this batch (it was committed,
                    # so they fused it): fusing it again would count it twice
                    return BatchResult(scans_fused=len(scans), rays=sum(_rays(scan) for scan in scans),
                                       cells_updated=0, version=version)
                # a batch that fails here keeps its version taken (the map's version skips it): a
                # later batch may have committed with the next one meanwhile, and should its
                # removal from the log have failed too, the row is still there under this version
                try:
                    result = await run(self._apply, entry, version, batch, prepared, cast_s)
                except BaseException:
                    # the map may have changed in part: a grid published for its
                    # current version would no longer be that map
                    self._grids.retire(entry.uid)
                    # and a later catch-up must not apply it (its row stays if its removal failed)
                    entry.checked = max(entry.checked, version)
                    raise
                # assigned here, on the event loop and under the apply lock, so that a reader and
                # MapInfo never pair the new arrays with the old version (or mix two versions)
                entry.version, entry.scans_fused, entry.updated = result.version, entry.map.scans_fused, updated
                if scans:  # a prior has none: the last scan stays the last one fused
                    entry.last_scan, entry.last_view = scans[-1], None
                self._grids.retire(entry.uid, below=entry.version)  # no plan will ask for an older one
                self._notify("batch_applied", entry.name, entry.version, entry.last_scan, entry.frame_id)
            if self._snapshot_due(entry):
                await self._snapshot_beside(entry)
            return result
        finally:
            # applied, or not (a failed catch-up leaves it in the log for the next one to apply)
            entry.inflight.discard(version)
            entry.line.done(ticket)

    async def replace_by_rebuild(self, name: str, incarnation: str | None, rebuilt: MapEntry,
                                 switch: Callable[[], int | None], catch_up: Callable[[], None]) -> int:
        """Replace map ``name`` by ``rebuilt`` (the same history fused again, caught up to the version it names),
        stored by ``switch`` (blocking: the rebuilt map's snapshot and the store's switch; None when a batch was
        stored since) after ``catch_up`` (blocking: the rebuilt map brought to the newest stored version) as often
        as it takes; the new version.

        Where this replica holds the map, in the map's line as a writer: no batch of it commits meanwhile, the
        batches committed before are applied to the current map first, and the rebuilt one takes its place under
        the apply lock, so a reader sees one or the other, whole. Where it does not, the holders catch up from the
        stored snapshot, as after another replica's snapshot.
        """
        entry = self._registry.holding(name)
        if entry is not None and entry.incarnation != incarnation:
            entry = None
        ticket = None if entry is None else entry.line.take()
        try:
            if entry is not None and ticket is not None:
                await entry.line.commit.wait(ticket)
            while (version := await self._workers.run_heavy(switch)) is None:
                await self._workers.run_heavy(catch_up)
            if entry is None or ticket is None:
                return version
            entry.line.commit.done(ticket)  # the next batch commits as the next version
            await entry.line.apply.wait(ticket)
            async with entry.apply_lock:
                entry.map, entry.updated, entry.scans_fused = rebuilt.map, rebuilt.updated, rebuilt.map.scans_fused
                entry.version = entry.snapshot_version = entry.checked = version
                entry.log.clear()  # a restart starts from the snapshot the switch stored
                if rebuilt.last_scan is not None:  # at its corrected pose
                    entry.last_scan = rebuilt.last_scan
                entry.last_view = None
                self._grids.retire(entry.uid, below=version)
                if entry.last_scan is not None:
                    self._notify("batch_applied", entry.name, entry.version, entry.last_scan, entry.frame_id)
            return version
        finally:
            if entry is not None and ticket is not None:
                entry.line.done(ticket)

    async def current(self, name: str) -> MapEntry:
        """The map for a read: with every batch acknowledged (by this replica or another) before the call applied.

        With SQLite this is the map held. With a shared database, the map's newest version is read from it
        first; batches of other replicas up to it are applied in the map's line, after this replica's own
        batches committed before them. Only this replica's batches still being fused lie ahead of a read
        that waits for nothing else: they are not acknowledged yet.
        """
        entry, newest = await self._registry.held(name, fresh=True)
        known = max(entry.version, entry.checked)
        ours = sum(1 for version in entry.inflight if known < version <= newest)
        if newest - known > ours:
            await self._catch_up(entry, newest)
        return entry

    async def _catch_up(self, entry: MapEntry, target: int) -> None:
        """Apply the stored batches up to ``target`` in the map's line, as a writer would."""
        ticket = entry.line.take()
        entry.line.commit.done(ticket)  # it commits nothing; a later batch commits after the version read
        entry.catching_up += 1
        try:
            await entry.line.apply.wait(ticket)
            if entry.deleted:
                raise NotFound(f"no map named {entry.name!r}")
            if target > max(entry.version, entry.checked):
                async with entry.apply_lock:
                    await self._catch_up_locked(entry, target)
        finally:
            entry.catching_up -= 1
            entry.line.done(ticket)

    async def _catch_up_locked(self, entry: MapEntry, target: int) -> None:
        """Bring the map to ``target`` from the store: the batches after its version, or a newer snapshot and the
        batches after that (another replica snapshotted, maybe folded the ones in between).

        The caller holds the map's apply turn and its apply lock.
        """
        stored = await self._workers.run(self.storage.load_since, entry.name, entry.version, target)
        if stored is None or stored.incarnation != entry.incarnation:
            raise await self._registry.gone(entry)
        if stored.damage:
            raise Unavailable(f"map {entry.name!r}: its stored log is damaged ({'; '.join(stored.damage)})")
        if stored.snapshot is not None:
            fresh = await self._workers.run(restore, stored, target)
            entry.map, entry.snapshot_version = fresh.map, fresh.snapshot_version
            entry.version, entry.updated, entry.last_scan = fresh.version, fresh.updated, fresh.last_scan
            entry.log = collections.deque([*fresh.log, *(item for item in entry.log if item[0] > fresh.version)])
        else:
            progress = await self._workers.run(
                functools.partial(replay, entry.map, stored, after=entry.version, up_to=target))
            entry.log.extend(progress.log)
            if progress.version:
                entry.version, entry.updated, entry.last_scan = progress.version, progress.updated, progress.last_scan
        entry.checked = max(entry.checked, min(target, stored.version))
        entry.scans_fused, entry.last_view = entry.map.scans_fused, None
        self.metrics.catch_ups.inc()
        self._grids.retire(entry.uid, below=entry.version)
        if entry.last_scan is not None:
            self._notify("batch_applied", entry.name, entry.version, entry.last_scan, entry.frame_id)



def _rays(scan: Scan) -> int:
    return len(scan.ranges) if isinstance(scan, LaserScan) else len(scan.points)


def _check_edit(entry: MapEntry, edit: Edit) -> None:
    """``Invalid`` for an edit the map cannot take (checked before it is stored: nothing changes on a refusal)."""
    if isinstance(edit, SetForget):
        if not isinstance(entry.map, FuzzyMap):
            raise Invalid("forget_beyond is for fuzzy maps; a bayes map holds its whole box")
        return
    dims = entry.spec.ndim
    for corner, values in (("min", edit.low), ("max", edit.high)):
        if len(values) != dims:
            raise Invalid(f"{corner} has {len(values)} coordinates; this map is {dims}-D")
        if not all(math.isfinite(v) and abs(v) <= MAX_COORDINATE_M for v in values):
            raise Invalid(f"{corner} must be finite coordinates within {MAX_COORDINATE_M:.0e} m of the frame's origin")
    low, high = np.asarray(edit.low), np.asarray(edit.high)
    if np.any(high < low):
        axis = int(np.flatnonzero(high < low)[0])
        raise Invalid(f"max[{axis}] = {high[axis]} is below min[{axis}] = {low[axis]}: give the box's lower corner "
                      "as min")
