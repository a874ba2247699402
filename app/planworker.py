"""What runs inside a planner worker process, and the pool that runs it.

OMPL's ``solve()`` holds the GIL for the whole solve, so plans never run on the
event loop's process: a bounded ``ProcessPoolExecutor`` (forkserver, or spawn where
there is no forkserver) receives the risk grid and the parameters, and returns
plain data. The forkserver imports the planner stack (OMPL, and numba's kernels compiled
at import) once; each worker forked from it warms the rest up as it starts.

A plan on a published grid (``app.plangrids``) gets only the grid's files with its parameters
(``run_shared_plan``), and the worker keeps the ``RiskField`` of each grid it planned on (with the
dilations computed for it) for the next plans on that map version; otherwise the arrays come with
the plan (``run_plan``).

The processes end with the server, however it ends: the forkserver is started from a
thread that lives as long as the server and asks Linux to kill it when the server ends
(``app.forkserver_preload``), each worker asks the same of the forkserver and also
watches the server itself (``app.lifecycle``). Without that, a server killed with
``kill -9`` leaves them all waiting for each other (each worker holds the pipe the
forkserver waits on, and waits for work itself).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import multiprocessing
import multiprocessing.forkserver
import os
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Literal, TypeVar

import numpy as np

from app import lifecycle
from app.errors import Unavailable
from app.plangrids import FieldCache, GridRef

LOG = logging.getLogger("fuzzyrisk.plans")
T = TypeVar("T")


#: Modules the forkserver imports before it forks any worker: first the one that ties its life to the
#: server's, then the planner stack (``planning.query`` compiles, or loads, numba's kernels as it is imported).
FORKSERVER_PRELOAD = ["app.forkserver_preload", "app.planworker", "planning.query"]
#: Seconds a worker that is not done when the pool shuts down (an abandoned plan) gets before it is ended.
SHUTDOWN_GRACE_S = 2.0

# Linux ties the forkserver's death signal to the thread that started it, so that thread must live as long
# as the process: this one never ends before the interpreter does (a request's thread may).
_FORKSERVER_STARTER = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="forkserver-start")


def _ensure_forkserver(context: multiprocessing.context.BaseContext) -> None:
    """Start the forkserver (if it is not running) from the long-lived starter thread; blocks."""
    if context.get_start_method() == "forkserver":
        _FORKSERVER_STARTER.submit(multiprocessing.forkserver.ensure_running).result()


#: In a worker: the barrier its pool's warm-up tasks meet at (``_warm``), so that each lands in its own worker.
_STARTED_TOGETHER: Any = None
#: Seconds the warm-up waits for all workers to be up (from numba's cache they start in seconds).
WARM_BARRIER_TIMEOUT_S = 120.0
#: Bytes of fields a worker keeps when its pool is not told (``PlanPool(field_cache_bytes=...)``).
DEFAULT_FIELD_CACHE_BYTES = 256 * 2**20
#: In a worker: the fields of the published grids it planned on (``run_shared_plan``).
_FIELDS = FieldCache(DEFAULT_FIELD_CACHE_BYTES)


def _init_worker(native: bool, together: Any = None, field_cache_bytes: int = DEFAULT_FIELD_CACHE_BYTES) -> None:
    """In each new worker: end with the server, use the compiled planner callbacks (``planning/native.py``)
    or not, and compile or load every kernel now, so that no plan waits for it."""
    global _STARTED_TOGETHER, _FIELDS
    lifecycle.die_with_parent()  # the forkserver, which dies with the server
    lifecycle.exit_with_parent()  # the server itself: other systems, or the forkserver gone before the line above
    _STARTED_TOGETHER = together
    _FIELDS = FieldCache(field_cache_bytes)
    import planning
    from planning import native as compiled

    # OMPL's plain-text warnings would break the service's one-JSON-object-a-line logs; what they
    # warn about comes back in each result (status, message) or is documented (planning/README.md)
    planning.quiet_ompl()
    compiled.set_enabled(native)
    planning.warm_up()  # its plans load (or compile) the compiled callbacks too


def _warm(together: bool = False) -> int:
    """A task that starts a worker (its initializer warms the planner stack up); the worker's pid.

    ``together``: wait until every worker of the pool runs one, so that tasks submitted together
    each start their own worker instead of being taken one after another by the first that is free.
    """
    if together and _STARTED_TOGETHER is not None:
        _STARTED_TOGETHER.wait(WARM_BARRIER_TIMEOUT_S)
    return os.getpid()


def _number(value: Any) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def run_plan(
    risk: np.ndarray, observed: np.ndarray, resolution: float, origin: tuple[float, ...], params: dict[str, Any]
) -> dict[str, Any]:
    """Plan on a risk grid (in a worker process); returns ``{"result": ...}`` or ``{"error": ...}``.

    ``params`` are ``planning.plan``'s keyword arguments. A start or goal the planner
    cannot use comes back as ``{"error": {"code": <Nav2 name>, "message": ...}}``, any
    other refusal of the parameters as ``{"invalid": message}``.
    """
    from planning import RiskField

    try:
        field = RiskField(risk, resolution, origin, observed=observed)
    except ValueError as exc:
        return {"invalid": str(exc)}
    return _plan_on(field, params)


def run_shared_plan(ref: GridRef, params: dict[str, Any]) -> dict[str, Any]:
    """``run_plan`` on a published grid: the field this worker kept for it, or one read from its files.

    The field keeps its dilations for the next plan on the same grid (``app.plangrids.FieldCache``).
    """
    field = _FIELDS.field(ref)
    try:
        return _plan_on(field, params)
    finally:
        _FIELDS.used(ref, params.get("robot_radius", 0.2), params.get("allow_unknown", True))


def worker_fields() -> dict[str, Any]:
    """What this worker keeps (for tests): the grids' risk files, their bytes, and how many fields it read."""
    return {"paths": _FIELDS.paths, "bytes": _FIELDS.nbytes, "loads": _FIELDS.loads, "max_bytes": _FIELDS.max_bytes,
            "pid": os.getpid()}


def _plan_on(field: Any, params: dict[str, Any]) -> dict[str, Any]:
    from planning import PlanError, plan

    try:
        result = plan(field, **params)
    except PlanError as exc:
        return {"error": {"code": str(exc.code), "message": str(exc)}}
    except ValueError as exc:
        return {"invalid": str(exc)}
    path = np.asarray(result.path, dtype=np.float64).reshape(-1, len(params["start"]))
    return {
        "result": {
            "status": str(result.status),
            "planner": str(result.planner),
            "state_space": str(result.state_space),
            "path": path.tolist(),
            "length": _number(result.length),
            "max_risk": _number(result.max_risk),
            "mean_risk": _number(result.mean_risk),
            "cost": _number(result.cost),
            "planning_time": float(result.planning_time),
            "message": str(result.message),
            "error_code": str(result.error_code) or None,
            "stopped_by": str(result.stopped_by),
            "iterations": int(result.iterations),
            "first_solution_time": _number(result.first_solution_time),
        }
    }


def _context() -> multiprocessing.context.BaseContext:
    # fork would copy the server's threads and locks into the child; forkserver forks a clean
    # process that has already imported the planner stack
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    context = multiprocessing.get_context(method)
    if method == "forkserver":
        context.set_forkserver_preload(FORKSERVER_PRELOAD)
    return context


class PlanPool:
    """At most ``workers`` plans run at once; up to ``queue`` more wait; beyond that, 503.

    ``field_cache_bytes``: what each worker may keep of the fields of published grids (``run_shared_plan``).
    """

    def __init__(self, *, workers: int, queue: int, native: bool = True,
                 field_cache_bytes: int = DEFAULT_FIELD_CACHE_BYTES) -> None:
        self._workers = workers
        self._queue = queue
        self._native = native
        self._field_cache_bytes = field_cache_bytes
        self._waiting = 0
        self._running = asyncio.Semaphore(workers)
        self._executor: concurrent.futures.ProcessPoolExecutor | None = None
        self._context = _context()
        self._warming: asyncio.Task[None] | None = None
        #: pids of the workers warmed up by ``start``
        self.warmed: set[int] = set()
        self.warm_error: str | None = None

    @property
    def warm_state(self) -> Literal["off", "starting", "ready", "failed"]:
        """``start`` never called, its workers starting, all warmed up, or failed (``warm_error`` says why)."""
        if self.warm_error is not None:
            return "failed"
        if self._warming is None:
            return "off"
        return "ready" if self._warming.done() else "starting"

    def start(self) -> None:
        """Start the worker processes in the background (otherwise they start at the first plan).

        One worker first: it compiles the planner kernels into numba's cache (or loads them); then the
        others, which load them. Compiled once, not once per worker at the same time.
        """
        self._warming = asyncio.get_running_loop().create_task(self._warm_up(self._ensure()))

    async def _warm_up(self, executor: concurrent.futures.ProcessPoolExecutor) -> None:
        loop = asyncio.get_running_loop()
        started = time.perf_counter()
        LOG.info("starting the planner workers (each compiles or loads its kernels)",
                 extra={"fields": {"workers": self._workers}})
        try:
            # submit() starts processes, and the first one waits for the forkserver to import the
            # planner stack (seconds): never on the event loop
            first = await loop.run_in_executor(None, self._submit, executor, _warm)
            self.warmed.add(await asyncio.wrap_future(first))
            LOG.info("planner worker ready", extra={"fields": {
                "workers_ready": 1, "workers": self._workers, "seconds": round(time.perf_counter() - started, 1)}})
            if self._workers > 1:  # the first worker is free again: it and each new one take one task
                others = [await loop.run_in_executor(None, self._submit, executor, _warm, True)
                          for _ in range(self._workers)]
                self.warmed.update(await asyncio.gather(*(asyncio.wrap_future(f) for f in others)))
        except Exception as exc:  # noqa: BLE001 - reported by readiness and the log, and again by the first plan
            self.warm_error = f"the planner workers did not start: {exc!r}"
            LOG.error(self.warm_error, exc_info=True)
            return
        LOG.info("planner workers ready", extra={"fields": {
            "workers_ready": len(self.warmed), "workers": self._workers,
            "seconds": round(time.perf_counter() - started, 1)}})

    def _submit(self, executor: concurrent.futures.ProcessPoolExecutor, fn: Callable[..., T], *args: Any
                ) -> concurrent.futures.Future[T]:
        """``executor.submit`` (which may start a worker), the forkserver started by the long-lived thread first."""
        _ensure_forkserver(self._context)
        return executor.submit(fn, *args)

    def _ensure(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._executor is None:
            # creating the executor starts no process; submit() does
            together = self._context.Barrier(self._workers)  # passed at start: a barrier cannot travel in a task
            self._executor = concurrent.futures.ProcessPoolExecutor(
                self._workers, mp_context=self._context, initializer=_init_worker,
                initargs=(self._native, together, self._field_cache_bytes),
            )
        return self._executor

    def _restart(self, broken: concurrent.futures.ProcessPoolExecutor) -> None:
        """Throw away the workers of ``broken`` (one is stuck or dead); the next plan starts afresh."""
        if self._executor is broken:
            self._executor = None
        # a stuck solve never returns: the only way to get its process back is to end it
        for process in list(getattr(broken, "_processes", {}).values()):
            process.terminate()
        broken.shutdown(wait=False, cancel_futures=True)

    async def run(self, fn: Callable[..., T], timeout_s: float, *args: Any) -> T:
        """``fn(*args)`` in a worker (``run_plan`` in the service); ``Unavailable`` when too busy, stuck or crashed."""
        if self._waiting >= self._queue + self._workers:
            raise Unavailable(
                f"{self._waiting} plans are already waiting or running; retry shortly "
                "(FUZZYRISK_PLAN_WORKERS, FUZZYRISK_PLAN_QUEUE)",
                headers={"Retry-After": "1"},
            )
        self._waiting += 1
        try:
            async with self._running:
                loop = asyncio.get_running_loop()
                for attempt in (1, 2):
                    executor = self._ensure()
                    try:
                        future = await loop.run_in_executor(None, self._submit, executor, fn, *args)
                        break
                    except BrokenProcessPool:
                        # a worker died while idle (the OOM killer, a kill): this plan has not run, so it
                        # may go to a new pool; without this, every later plan would fail the same way
                        LOG.error("a planner worker had died; restarting the workers")
                        self._restart(executor)
                        if attempt == 2:
                            raise Unavailable("the planner workers stopped unexpectedly; retry") from None
                try:
                    return await asyncio.wait_for(asyncio.wrap_future(future), timeout_s)
                except TimeoutError:
                    LOG.error("planner worker did not answer in %.1f s; restarting the workers", timeout_s)
                    self._restart(executor)
                    raise Unavailable(f"the planner did not finish within {timeout_s:.1f} s; retry") from None
                except BrokenProcessPool:
                    LOG.error("a planner worker died; restarting the workers")
                    self._restart(executor)
                    raise Unavailable("the planner worker stopped unexpectedly; retry") from None
        finally:
            self._waiting -= 1

    def shutdown(self) -> None:
        """Stop the workers: idle ones at once, one still busy (a plan whose request the graceful shutdown
        gave up on, or a warm-up) after ``SHUTDOWN_GRACE_S``, so that a stop fits ``docker stop``'s time."""
        if self._warming is not None:
            self._warming.cancel()
        executor, self._executor = self._executor, None
        if executor is None:
            return
        processes = list(getattr(executor, "_processes", {}).values())
        executor.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + SHUTDOWN_GRACE_S
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
        for process in processes:
            if process.is_alive():
                process.terminate()
                process.join(5.0)
            if process.is_alive():
                process.kill()
                process.join(5.0)
