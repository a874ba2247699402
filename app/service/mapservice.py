"""The service: the maps it holds, their write path, their reads and their plans, started and stopped together.

``MapService`` only wires the parts and runs the lifecycle; each part is a module of its own:

* ``app.maps.registry``: which maps exist (create, list, delete, load at start, quarantine);
* ``app.maps.writepath``: batches in order through commit, apply and snapshot (its docstring has the
  concurrency and durability rules);
* ``app.reads.service``: every output of a map, consistent with one version;
* ``app.plans.service``: plans in the planner worker processes;
* ``app.plans.path_check``: paths checked under a plan's rules, where reads run.

HTTP handlers call those parts through ``MapService``'s attributes (``maps``, ``writes``, ``reads``,
``plans``, ``path_checks``); it is the only bridge from HTTP to ``fuzzyocc`` and ``planning``.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import os
from typing import Any

from app.ros import msgtypes
from app.ops import warmup
from app.config import Settings
from app.storage.diskreserve import DiskReserve
from app.ops.process_setup import give_back_freed_memory
from app.maps import MapObserver, MapRegistry, PlanGrids, WritePath
from app.maps.shared_grids import DIRECTORY as PLAN_GRIDS_DIRECTORY
from app.maps.refusion import Refusions
from app.ops.metrics import Metrics
from app.plans.path_check import PathChecks
from app.plans.service import MapPlans
from app.plans.pool import PlanPool
from app.reads.service import MapReads
from app.schemas import Readiness
from app.storage import Storage
from app.ops.threads import Workers
from fuzzyocc import parallel

LOG = logging.getLogger("fuzzyrisk.maps")


class MapService:
    """Named maps in memory, backed by ``Storage``; fusion in threads, plans in processes."""

    def __init__(self, settings: Settings, storage: Storage, metrics: Metrics) -> None:
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        self._workers = Workers(fusion_threads=settings.fusion_threads, read_threads=settings.read_threads)
        parallel.set_threads(settings.split_threads or None)
        self._pool = PlanPool(
            workers=settings.plan_workers, queue=settings.plan_queue, per_map=settings.plan_workers_per_map,
            native=settings.native_planning,
            field_cache_bytes=settings.plan_cache_bytes,
        )
        # map versions published for the planner workers, so that a plan does not copy its map's grid
        self._grids = PlanGrids(settings.data_dir / PLAN_GRIDS_DIRECTORY, settings.plan_cache_bytes, self._workers.run,
                                metrics.plan_grid_bytes.set)
        self._reserve = DiskReserve(settings.data_dir, settings.disk_reserve_bytes)
        self.maps = MapRegistry(settings, storage, metrics, self._workers, self._grids, self._reserve, self._notify)
        self.writes = WritePath(settings, storage, metrics, self._workers, self.maps, self._grids, self._notify)
        self.reads = MapReads(settings, storage, self._workers, self.writes.current)
        self.plans = MapPlans(settings, metrics, self.writes.current, self.reads, self._grids, self._pool,
                              self._notify)
        self.path_checks = PathChecks(settings, self.reads)
        self.refusions = Refusions(settings, storage, metrics, self._workers, self.maps, self.writes)
        metrics.batches_in_line.set_function(self.maps.batches_in_line)
        metrics.longest_fusion_job.set_function(self._workers.longest_fusion_job_s)
        self._kernels: asyncio.Task[None] | None = None
        self._kernels_error: str | None = None
        self._evictor: asyncio.Task[None] | None = None
        #: told of batches applied, plans made and maps deleted (``MapObserver``); None: nobody
        self.observer: MapObserver | None = None

    def _notify(self, event: str, *args: Any) -> None:
        """Tell the observer, if any; its failure is logged and goes no further (the change is done)."""
        if self.observer is not None:
            try:
                getattr(self.observer, event)(*args)
            except Exception:  # noqa: BLE001 - a viewer's bug must not fail a batch, a plan or a delete
                LOG.exception("map observer failed on %s", event)

    async def start(self) -> None:
        """Load every stored map (snapshot + replay) and, if configured, start the planner workers."""
        await self._workers.run(self._grids.open)  # and remove what a killed run left
        await self._workers.run(self._reserve.hold)
        await self.maps.load_all()
        self.refusions.start()  # corrections left pending by a killed run resume once their lease runs out
        # in the background: /health answers meanwhile, /ready once they are done; a scan that comes first
        # waits for the kernel it needs (numba compiles one at a time), not for all of them
        self._kernels = asyncio.get_running_loop().create_task(self._warm_kernels())
        if self.settings.plan_warmup:
            self._pool.start()
        if self.settings.shared_storage:
            self._evictor = asyncio.get_running_loop().create_task(self._evict_idle())

    async def _evict_idle(self) -> None:
        """A replica's memory holds the maps it serves: every so often, drop those idle for FUZZYRISK_MAP_IDLE_S."""
        while True:
            await asyncio.sleep(min(60.0, self.settings.map_idle_s / 2))
            if dropped := self.maps.evict_idle():
                LOG.info("idle maps dropped from memory", extra={"fields": {"maps": dropped}})
                await self._workers.run_admin(give_back_freed_memory)

    async def _warm_kernels(self) -> None:
        """Compile the fusion kernels, or load them from numba's cache, in a fusion thread, with progress in the log."""
        LOG.info("compiling the fusion kernels, or loading them from numba's cache (a first start compiles for "
                 "about 20 s)", extra={"fields": {"cache": os.environ.get("NUMBA_CACHE_DIR", "numba's default")}})

        def progress(step: str, seconds: float) -> None:
            LOG.info("kernels ready: %s", step, extra={"fields": {"seconds": round(seconds, 2)}})

        try:
            seconds = await self._workers.run(warmup.warm_fusion, progress)
            # the ROS message types too: built at the first CDR body or OccupancyGrid, they held the GIL for
            # 0.1-0.3 s in the middle of serving (and came after the freeze below)
            await self._workers.run(msgtypes.typestore)
        except Exception as exc:  # noqa: BLE001 - a bug: readiness reports it; requests report their own
            self._kernels_error = f"the fusion kernels did not compile: {exc!r}"
            LOG.error(self._kernels_error, exc_info=True)
            return
        LOG.info("fusion kernels ready", extra={"fields": {"seconds": round(seconds, 2)}})
        # What exists now (modules, compiled kernels, the maps loaded) lives as long as the process: out of the
        # collector's sight, a full collection no longer walks it. Each one took about 100 ms holding the GIL,
        # every request of every client waiting (the innocent's scan and read p99 of bench abuse).
        # Freed by reference counting as before (a map is no reference cycle); collected first, so that no
        # garbage is frozen with it.
        gc.collect()
        gc.freeze()

    def readiness(self) -> Readiness:
        """Ready for traffic: maps loaded (always, once the service answers), fusion kernels compiled or loaded,
        and the planner workers up and warmed (when FUZZYRISK_PLAN_WARMUP starts them with the service)."""
        kernels = self._kernels is not None and self._kernels.done() and self._kernels_error is None
        planners = self._pool.warm_state
        problems = [p for p in (self._kernels_error, self._pool.warm_error) if p]
        if problems:
            status = "failed"
        elif kernels and planners in ("off", "ready"):
            status = "ready"
        else:
            status = "starting"
        return Readiness(
            status=status, maps_loaded=len(self.maps.held_maps), maps_quarantined=self.maps.quarantined,
            kernels_compiled=kernels,
            planner_workers_ready=len(self._pool.warmed),
            planner_workers_wanted=self.settings.plan_workers if self.settings.plan_warmup else 0,
            batches_in_line=self.maps.batches_in_line(),
            longest_fusion_job_s=round(self._workers.longest_fusion_job_s(), 3),
            detail="; ".join(problems),
        )

    async def stop(self) -> None:
        """Wait for batches in flight, snapshot every map with unsnapshotted batches, release everything."""
        if self._evictor is not None:
            self._evictor.cancel()
        await self.refusions.stop()
        await self.writes.stop()
        if self._kernels is not None:
            self._kernels.cancel()  # a compilation under way still ends in its thread (below)
        self._pool.shutdown()
        gc.unfreeze()  # the collector may free what this service leaves (another service may run in this process)
        self._workers.shutdown()  # grids being written included
        self._grids.close()
        self.storage.close()
