"""Re-fusion after a loop closure: a corrected trajectory stored, the map rebuilt from its history at it, switched.

``Refusions.correct`` (``PUT /maps/{name}/trajectory``) reads the poses and stamps of the map's history, gives each
scan in the trajectory's range its corrected pose (``app.maps.correction``), and stores that durably as the map's
pending correction before it answers. A background job then rebuilds the map: the whole history (from its base, or
from the creation) fused again, each moved batch at its new poses, in a heavy fusion thread (niced: the live maps'
batches and reads come first). Batches that arrive meanwhile go to the live map as usual and, from the store, to the
rebuilt one before the switch. The switch (``WritePath.replace_by_rebuild``, ``Storage.switch_reposed``) stores the
moved poses with their batches, a ``Reposed`` record as the next version and the rebuilt map as the restart snapshot
at it, in one transaction; the live map is then replaced under its apply lock. Until then every read and plan is
served from the current map.

One job per map: a new correction supersedes the pending one (its job stops at its next batch). The job holds the
correction by a lease in the store (``FUZZYRISK_REBUILD_LEASE_S``, renewed with each progress report), so that after a ``kill -9`` (or
on a fleet, the death of the replica running it) the first replica to find the lease run out (``SWEEP_S``) resumes
it, from the start of the history; a correction is applied once, by whoever switches first.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

from app.config import Settings
from app.errors import Conflict, Invalid, NotFound, Unavailable
from app.maps import correction, ingest_process, logcodec, snapshotcodec
from app.maps.entry import MapEntry, now
from app.maps.logcodec import Reposed
from app.maps.registry import MapRegistry
from app.maps.stored import replay, restore
from app.maps.writepath import WritePath
from app.ops.metrics import Metrics
from app.ops.threads import Workers
from app.schemas import RebuildState, RebuildStatus
from app.storage import MapGone, Storage, StorageUnavailable, StoredMap, Superseded, Switch
from app.storage.corrections import DONE, FAILED, PENDING, StoredCorrection
from fuzzyocc import parallel
from fuzzyocc.tf import NotLevel

LOG = logging.getLogger("fuzzyrisk.maps")

#: Seconds between a job's progress reports (each renews its lease; the status of other replicas reads them).
REPORT_S = 1.0
#: Seconds between two looks for corrections whose owner is gone.
SWEEP_S = 2.0


class _Stopped(Exception):
    """The job was told to stop (superseded, deleted, the service stopping)."""


@dataclass
class _Job:
    """A rebuild under way in this process: its progress, read by the status without the store."""

    name: str
    id: str
    started: float = field(default_factory=time.time)
    reposed: int = 0
    done: int = 0
    total: int = 0
    stop: bool = False
    task: asyncio.Task[None] | None = None

    def report(self, stored: StoredCorrection | None = None) -> dict[str, Any]:
        base = {} if stored is None else stored.report
        return {**base, "scans_reposed": self.reposed, "scans_done": self.done, "scans_total": self.total,
                "started": self.started, "elapsed_s": round(time.time() - self.started, 3)}

    def tick(self, scans: int) -> None:
        """``restore``'s progress, in the fusion thread: counts, and stops the replay when told to."""
        if self.stop:
            raise _Stopped(self.name)
        self.done += scans


class Refusions:
    """Maps rebuilt at corrected trajectories: the corrections taken in, their jobs, their status."""

    def __init__(self, settings: Settings, storage: Storage, metrics: Metrics, workers: Workers,
                 registry: MapRegistry, writes: WritePath) -> None:
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        self._workers = workers
        self._registry = registry
        self._writes = writes
        #: this process among the replicas: the owner of the corrections it works on
        self.owner = uuid.uuid4().hex
        self._jobs: dict[str, _Job] = {}
        self._sweeper: asyncio.Task[None] | None = None

    def start(self) -> None:
        """Look for corrections left pending (a restart after a kill, a replica gone) now and every ``SWEEP_S``."""
        self._sweeper = asyncio.get_running_loop().create_task(self._sweep())

    async def stop(self) -> None:
        """Stop the jobs at their next batch (their corrections stay pending: the next start resumes them)."""
        if self._sweeper is not None:
            self._sweeper.cancel()
        jobs = [job for job in self._jobs.values() if job.task is not None]
        for job in jobs:
            job.stop = True
        if jobs:
            await asyncio.wait([job.task for job in jobs if job.task is not None])

    async def _sweep(self) -> None:
        while True:
            try:
                orphans = await self._workers.run_admin(self.storage.correction_orphans, time.time())
                for name, correction_id in orphans:
                    job = self._jobs.get(name)
                    if job is None or job.id != correction_id:
                        self._begin(name, correction_id)
            except StorageUnavailable as exc:
                LOG.warning("could not look for pending corrections", extra={"fields": {"error": str(exc)}})
            await asyncio.sleep(SWEEP_S)

    # ------------------------------------------------------------------ a correction taken in

    async def correct(self, name: str, body: bytes, offset: correction.SensorOffset | None) -> RebuildStatus:
        """Store the correction a ``CorrectedPath`` JSON ``body`` (with the sensor's ``offset`` on the robot, if
        given) makes to map ``name``'s history and start its rebuild.

        ``RequestValidationError`` for a body that is not a ``CorrectedPath``; ``TooLarge`` past
        ``FUZZYRISK_MAX_TRAJECTORY_POSES`` poses; ``Invalid`` for a path that is not a trajectory in the map's frame
        (``correction.sensor_trajectory``) or a pose in range that tilts the scanner off level; ``Conflict`` when no
        stored scan has a stamp in its range, or a point cloud does.
        """
        entry = await self._writes.current(name)
        args = (body, entry.frame_id, offset, self.settings.max_trajectory_poses)
        if ingest_process.wants(body):
            trajectory = await self._writes.parse_process.run(correction.read_trajectory, *args)
        else:
            trajectory = await self._workers.run_parser(correction.read_trajectory, *args)
        through, incarnation = entry.version, entry.incarnation
        history = await self._workers.run_heavy(self.storage.load_history, name, through)
        if history is None or history.incarnation != incarnation:
            raise NotFound(f"no map named {name!r}; GET /maps lists them")
        if history.damage:
            raise Unavailable(f"map {name!r}: its stored log is damaged ({'; '.join(history.damage)})")
        try:
            change = await self._workers.run_heavy(correction.plan, history, trajectory, through)
        except (correction.NothingToCorrect, correction.CannotRepose) as exc:
            raise Conflict(str(exc)) from None
        except NotLevel as exc:
            raise Invalid(f"poses: {exc}") from None
        except logcodec.CorruptBatch as exc:
            raise Unavailable(f"map {name!r}: a stored batch is corrupt ({exc})") from None
        correction_id, requested = uuid.uuid4().hex, now()
        try:
            await self._workers.run_admin(
                self.storage.put_correction, name, incarnation, correction_id, through, correction.encode(change),
                requested, self.owner, time.time() + self.settings.rebuild_lease_s)
        except MapGone:
            raise NotFound(f"no map named {name!r}; GET /maps lists them") from None
        LOG.info("trajectory correction stored; rebuilding", extra={"fields": {
            "map": name, "correction": correction_id, "through_version": through, "scans_reposed": change.scans}})
        self._begin(name, correction_id, change.scans)
        return await self.status(name)

    def _begin(self, name: str, correction_id: str, reposed: int = 0) -> None:
        """Start the job of a correction, stopping the map's job before it (superseded)."""
        before = self._jobs.get(name)
        if before is not None:
            before.stop = True
        job = _Job(name, correction_id, reposed=reposed)
        self._jobs[name] = job
        job.task = asyncio.get_running_loop().create_task(self._run(job, None if before is None else before.task))

    # ------------------------------------------------------------------ the job

    async def _run(self, job: _Job, before: asyncio.Task[None] | None) -> None:
        result = "superseded"
        reporter = asyncio.get_running_loop().create_task(self._report(job))
        try:
            if before is not None:
                # the superseded rebuild stops at its next batch: one rebuilt copy of the map at a time (five PUTs
                # in a row on a map of one long batch held five copies side by side)
                await asyncio.wait([before])
            if job.stop:
                raise _Stopped(job.name)
            result = await self._rebuild(job)
        except (_Stopped, Superseded, MapGone):
            pass
        except Exception as exc:  # noqa: BLE001 - whatever stops the rebuild is its failure, stored and reported
            result = "failed"
            LOG.exception("rebuild failed", extra={"fields": {"map": job.name, "correction": job.id}})
            with contextlib.suppress(Exception):
                await self._workers.run_admin(self.storage.fail_correction, job.name, job.id,
                                              {**job.report(), "error": f"{type(exc).__name__}: {exc}"})
        finally:
            reporter.cancel()
            if self._jobs.get(job.name) is job:
                del self._jobs[job.name]
            self.metrics.rebuilds.labels(result).inc()

    async def _report(self, job: _Job) -> None:
        """Every ``REPORT_S``: the progress stored, the lease renewed; a correction no longer this job's stops it."""
        while True:
            await asyncio.sleep(REPORT_S)
            try:
                mine = await self._workers.run_admin(self.storage.report_correction, job.name, job.id, self.owner,
                                                     time.time() + self.settings.rebuild_lease_s, job.report())
            except StorageUnavailable:
                continue  # the lease may run out: another replica then takes over, and this one stops at its switch
            if not mine:
                job.stop = True
                return

    async def _rebuild(self, job: _Job) -> str:
        claimed = await self._workers.run_admin(self.storage.claim_correction, job.name, job.id, self.owner,
                                                time.time() + self.settings.rebuild_lease_s, time.time())
        stored = await self._workers.run_read(functools.partial(self.storage.correction, job.name, with_payload=True))
        if not claimed or stored is None or stored.id != job.id or stored.state != PENDING or stored.payload is None:
            raise _Stopped(job.name)
        if stored.damage:
            raise RuntimeError(stored.damage)
        change = correction.decode(stored.payload)
        job.reposed = change.scans
        head = await self._workers.run_read(self.storage.map_head, job.name)
        if head is None:
            raise _Stopped(job.name)
        job.total = head.history_scans
        history = await self._workers.run_heavy(self.storage.load_history, job.name)
        if history is None or history.incarnation != head.incarnation:
            raise _Stopped(job.name)
        if history.damage:
            raise RuntimeError(f"the map's stored history is damaged: {'; '.join(history.damage)}")
        correction.apply(history, change)
        base = history.snapshot_version
        rebuilt = await self._workers.run_heavy(restore, history, None, job.tick)
        moved = [(version, history.poses[version]) for version in change.moves]
        marker = logcodec.encode_edit(Reposed(job.id, change.through, change.scans))
        rebuilt_at = _Caught(history.version)
        snapshots: dict[int, bytes] = {}

        def switch() -> int | None:
            if job.stop:
                raise _Stopped(job.name)
            if rebuilt_at.version not in snapshots:
                snapshots.clear()
                # the rebuilt map is this job's alone until the switch: its arrays are encoded in place (a copy
                # of a 39 MB map took 0.16 s of a 2.4 s rebuild), on every core the fusion may use
                snapshots[rebuilt_at.version] = snapshotcodec.encode(rebuilt.map.snapshot_arrays(copy=False),
                                                                     threads=parallel.threads())
            updated = now()
            report = job.report(stored)
            version = self.storage.switch_reposed(
                job.name, head.incarnation,
                Switch(job.id, rebuilt_at.version, base, moved, marker, updated, report),
                snapshots[rebuilt_at.version])
            if version is not None:
                rebuilt.updated = updated
            return version

        def catch_up() -> None:
            if job.stop:
                raise _Stopped(job.name)
            rebuilt_at.version = _catch_up(self.storage, job.name, rebuilt, rebuilt_at.version)

        await self._workers.run_heavy(catch_up)  # most of what came meanwhile, before the map's line is held
        version = await self._writes.replace_by_rebuild(job.name, head.incarnation, rebuilt, switch, catch_up)
        LOG.info("map rebuilt at the corrected trajectory", extra={"fields": {
            "map": job.name, "correction": job.id, "version": version, "scans": job.done,
            "seconds": round(time.time() - job.started, 3)}})
        return "done"

    # ------------------------------------------------------------------ status

    async def status(self, name: str) -> RebuildStatus:
        """The map's latest rebuild (``GET /maps/{name}/rebuild``)."""
        await self._registry.held(name)  # 404 for no map
        stored = await self._workers.run_read(self.storage.correction, name)
        if stored is None:
            return RebuildStatus(state=RebuildState.NONE)
        job = self._jobs.get(name)
        report = job.report(stored) if job is not None and job.id == stored.id and stored.state == PENDING \
            else stored.report
        state = {PENDING: RebuildState.RUNNING, DONE: RebuildState.DONE, FAILED: RebuildState.FAILED}[stored.state]
        done, total = int(report.get("scans_done", 0)), int(report.get("scans_total", 0))
        started = report.get("started")
        elapsed = float(report.get("elapsed_s", 0.0))
        if state is RebuildState.RUNNING and started is not None:
            elapsed = max(elapsed, time.time() - float(started))
        eta = None
        if state is RebuildState.RUNNING and done > 0 and total >= done:
            eta = round(elapsed / done * (total - done), 3)
        change_scans = report.get("scans_reposed")
        return RebuildStatus(
            state=state, id=stored.id, requested=stored.requested, from_version=stored.through_version,
            scans_reposed=int(change_scans) if change_scans is not None else 0, scans_done=done, scans_total=total,
            elapsed_s=round(elapsed, 3), eta_s=eta, version=stored.version, error=report.get("error"))


@dataclass
class _Caught:
    """The stored version a rebuilt map holds every batch up to (tombstones included)."""

    version: int


def _catch_up(storage: Storage, name: str, rebuilt: MapEntry, after: int) -> int:
    """Fuse the batches stored after version ``after`` into ``rebuilt`` (at their posted poses: the correction moved
    only those before); the newest stored version it now holds."""
    stored: StoredMap | None = storage.load_history(name, after=after)
    if stored is None:
        raise MapGone(name)
    if stored.damage:
        raise RuntimeError(f"the map's stored log is damaged: {'; '.join(stored.damage)}")
    if stored.snapshot is not None:  # the base moved past ``after``: folds wait for a pending correction
        raise Superseded(name)
    done = replay(rebuilt.map, stored, after=after)
    if done.version:
        rebuilt.version, rebuilt.updated = done.version, done.updated
    if done.last_scan is not None:
        rebuilt.last_scan = done.last_scan
    return max(after, stored.version)
