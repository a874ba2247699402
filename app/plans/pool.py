"""The pool of planner worker processes: plans queued fairly by map, each solved in a worker (``app.plans.worker``).

OMPL's ``solve()`` holds the GIL for the whole solve, so plans never run on the
event loop's process: each worker is a process of its own (a one-process
``ProcessPoolExecutor``, forkserver, or spawn where there is no forkserver) that receives
the risk grid and the parameters, and returns plain data. One worker per executor, so that a
stuck or dead worker is ended and replaced alone: the plans of the others go on. The
forkserver imports the planner stack (OMPL, and numba's kernels compiled at import) once;
each worker forked from it warms the rest up as it starts.

Waiting plans take free workers in turns by map (round robin), and one map holds at most
half the queue, so a client that floods one map with plans does not delay or refuse another's.

The processes end with the server, however it ends: the forkserver is started from a
thread that lives as long as the server and asks Linux to kill it when the server ends
(``app.ops.forkserver_preload``), each worker asks the same of the forkserver and also
watches the server itself (``app.ops.process_setup``). Without that, a server killed with
``kill -9`` leaves them all waiting for each other (each worker holds the pipe the
forkserver waits on, and waits for work itself).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Literal, TypeVar

from app.errors import Unavailable
from app.ops.forkserver import ensure_forkserver, worker_context
from app.plans.worker import DEFAULT_FIELD_CACHE_BYTES, init_worker, worker_pid

LOG = logging.getLogger("fuzzyrisk.plans")
T = TypeVar("T")


#: Seconds a worker that is not done when the pool shuts down (an abandoned plan) gets before it is ended.
SHUTDOWN_GRACE_S = 2.0

#: Seconds a plan that finds its share of the queue full waits for room before the 503 (its ``Retry-After``).
#: A client that ignores ``Retry-After`` and asks again at once is paced by it: ten clients asking back to
#: back for plans on one map made 90 requests a second, each refusal about 0.7 ms of the event loop, and an
#: innocent client's reads of another map 3.2x slower at the 99th percentile (``bench/bench_abuse.py``, scenario 9).
ROOM_WAIT_S = 1.0


class _Worker:
    """One planner process (a one-process executor, started at its first task): replaced alone."""

    def __init__(self, index: int) -> None:
        self.index = index
        self.lock = threading.Lock()
        self.executor: concurrent.futures.ProcessPoolExecutor | None = None
        self.last_key: str | None = None  # the map of its last plan: its field cache may hold that grid

    def processes(self) -> list[Any]:
        executor = self.executor
        return [] if executor is None else list(getattr(executor, "_processes", {}).values())

    def end(self) -> None:
        """End the process now (a stuck solve never returns: ending it is the only way to get it back)."""
        with self.lock:
            executor, self.executor = self.executor, None
        if executor is None:
            return
        processes = list(getattr(executor, "_processes", {}).values())
        for process in processes:
            process.terminate()
        executor.shutdown(wait=False, cancel_futures=True)


def default_per_map(workers: int) -> int:
    """Workers one map's plans may hold at once when not configured: all but one (at least one)."""
    return max(1, workers - 1)


class PlanPool:
    """At most ``workers`` plans run at once, each in a worker process of its own, one map's on at most
    ``per_map`` of them; up to ``queue`` more wait, each map at most half of them (at least one); a plan
    beyond that waits up to ``ROOM_WAIT_S`` for room, then 503.

    ``per_map`` (default ``default_per_map``): a map flooded with plans leaves a worker to the other maps,
    whose plans then wait for no solve of it, and leaves a core to the service's scans and reads (with both
    cores solving one map's plans, an innocent map's scan p99 was 2.1x: ``bench/bench_abuse.py``, scenario 9).
    ``field_cache_bytes``: what each worker may keep of the fields of published grids (``run_shared_plan``).
    """

    def __init__(self, *, workers: int, queue: int, per_map: int | None = None, native: bool = True,
                 field_cache_bytes: int = DEFAULT_FIELD_CACHE_BYTES) -> None:
        self._queue = queue
        self._per_key_queue = max(1, queue // 2)
        self._per_key_running = min(workers, per_map or default_per_map(workers))
        self._running: collections.Counter[str] = collections.Counter()  # map -> workers its plans hold
        self._native = native
        self._field_cache_bytes = field_cache_bytes
        self._workers = [_Worker(i) for i in range(workers)]
        self._free: list[_Worker] = list(self._workers)
        self._waiters: dict[str, collections.deque[asyncio.Future[_Worker]]] = {}
        self._turns: collections.deque[str] = collections.deque()  # maps with waiting plans, in turn order
        self._room: list[asyncio.Future[None]] = []  # plans waiting for room in the queue (``ROOM_WAIT_S``)
        self._context = worker_context()
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

    @property
    def waiting(self) -> int:
        """Plans waiting for a worker."""
        return sum(len(q) for q in self._waiters.values())

    def start(self) -> None:
        """Start the worker processes in the background (otherwise each starts at its first plan).

        One worker first: it compiles the planner kernels into numba's cache (or loads them); then the
        others, which load them. Compiled once, not once per worker at the same time.
        """
        self._warming = asyncio.get_running_loop().create_task(self._warm_up())

    async def _warm_up(self) -> None:
        loop = asyncio.get_running_loop()
        started = time.perf_counter()
        LOG.info("starting the planner workers (each compiles or loads its kernels)",
                 extra={"fields": {"workers": len(self._workers)}})

        async def warm(worker: _Worker) -> int:
            # submit() starts the process, and the first waits for the forkserver to import the planner
            # stack (seconds): never on the event loop
            future = await loop.run_in_executor(None, self._submit, worker, worker_pid)
            return await asyncio.wrap_future(future)

        try:
            first, *others = self._workers
            self.warmed.add(await warm(first))
            LOG.info("planner worker ready", extra={"fields": {
                "workers_ready": 1, "workers": len(self._workers),
                "seconds": round(time.perf_counter() - started, 1)}})
            self.warmed.update(await asyncio.gather(*(warm(w) for w in others)))
        except Exception as exc:  # noqa: BLE001 - reported by readiness and the log, and again by the first plan
            self.warm_error = f"the planner workers did not start: {exc!r}"
            LOG.error(self.warm_error, exc_info=True)
            return
        LOG.info("planner workers ready", extra={"fields": {
            "workers_ready": len(self.warmed), "workers": len(self._workers),
            "seconds": round(time.perf_counter() - started, 1)}})

    def _submit(self, worker: _Worker, fn: Callable[..., T], *args: Any) -> concurrent.futures.Future[T]:
        """``submit`` to the worker's executor (made here; the forkserver started by the long-lived thread first)."""
        ensure_forkserver(self._context)
        with worker.lock:  # the warm-up and a plan may submit to one worker from two threads at once
            if worker.executor is None:
                # creating the executor starts no process; submit() does
                worker.executor = concurrent.futures.ProcessPoolExecutor(
                    1, mp_context=self._context, initializer=init_worker,
                    initargs=(self._native, self._field_cache_bytes),
                )
            return worker.executor.submit(fn, *args)

    def _can_take(self, key: str) -> bool:
        return bool(self._free) and self._running[key] < self._per_key_running

    def _take_free(self, key: str) -> _Worker | None:
        """A free worker (the one that last planned on ``key`` if it is free) if this map holds fewer than
        ``per_map``."""
        if not self._can_take(key):
            return None
        worker = next((w for w in self._free if w.last_key == key), self._free[0])
        self._free.remove(worker)
        self._running[key] += 1
        return worker

    async def _acquire(self, key: str) -> _Worker:
        """A free worker, or wait for this map's turn (when the queue has room, or comes to have it soon)."""
        if (worker := self._take_free(key)) is not None:
            return worker
        if not await self._room_for(key):
            mine = len(self._waiters.get(key, ()))
            running = sum(self._running.values())
            raise Unavailable(
                f"{running} plans are running ({self._running[key]} of them on this map, which may hold "
                f"{self._per_key_running} of the {len(self._workers)} workers) and {self.waiting} waiting "
                f"({mine} of them on this map); retry shortly (FUZZYRISK_PLAN_WORKERS, "
                "FUZZYRISK_PLAN_WORKERS_PER_MAP, FUZZYRISK_PLAN_QUEUE)",
                headers={"Retry-After": str(math.ceil(ROOM_WAIT_S))},
            )
        if (worker := self._take_free(key)) is not None:  # came free while this plan waited for room
            return worker
        waiting = self._waiters.setdefault(key, collections.deque())
        turn: asyncio.Future[_Worker] = asyncio.get_running_loop().create_future()
        waiting.append(turn)
        if key not in self._turns:
            self._turns.append(key)
        try:
            return await turn
        except asyncio.CancelledError:
            if turn.done() and not turn.cancelled():
                self._release(turn.result(), key)  # handed over as the request went away: pass it on
            elif turn in waiting:  # else a release has already dropped it (it skips cancelled turns)
                waiting.remove(turn)
                if not waiting and self._waiters.get(key) is waiting:
                    del self._waiters[key]
                    self._turns.remove(key)
                self._made_room()
            raise

    def _admissible(self, key: str) -> bool:
        """A worker is free for ``key``'s plan, or its map's share of the queue has room."""
        full = len(self._waiters.get(key, ())) >= self._per_key_queue or self.waiting >= self._queue
        return self._can_take(key) or not full

    async def _room_for(self, key: str) -> bool:
        """Whether ``key``'s plan may take a worker or wait in the queue: at once, or after up to ``ROOM_WAIT_S``."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + ROOM_WAIT_S
        while not self._admissible(key):
            remaining = deadline - loop.time()
            if remaining <= 0:
                return False
            room: asyncio.Future[None] = loop.create_future()
            self._room.append(room)
            try:
                await asyncio.wait_for(room, remaining)
            except TimeoutError:
                return self._admissible(key)
            finally:
                if room in self._room:
                    self._room.remove(room)
        return True

    def _made_room(self) -> None:
        """A waiting plan left the queue, or a worker came free: those waiting for room look again."""
        room, self._room = self._room, []
        for future in room:
            if not future.done():
                future.set_result(None)

    def _release(self, worker: _Worker, key: str) -> None:
        """``key``'s plan is done with the worker: hand it to the next map in turn (round robin over the maps
        with waiting plans that hold fewer than ``per_map`` workers), or free it."""
        self._running[key] -= 1
        if not self._running[key]:
            del self._running[key]
        for _ in range(len(self._turns)):
            turn_key = self._turns.popleft()
            if self._running[turn_key] >= self._per_key_running:
                self._turns.append(turn_key)  # at its share: its turn comes when one of its plans ends
                continue
            waiting = self._waiters[turn_key]
            while waiting and waiting[0].done():  # cancelled while waiting
                waiting.popleft()
            if not waiting:
                del self._waiters[turn_key]
                continue
            turn = waiting.popleft()
            if waiting:
                self._turns.append(turn_key)  # its next plan waits for the other maps' turns
            else:
                del self._waiters[turn_key]
            self._running[turn_key] += 1
            turn.set_result(worker)
            self._made_room()
            return
        self._free.append(worker)
        self._made_room()

    async def run(self, fn: Callable[..., T], timeout_s: float, *args: Any, key: str = "") -> T:
        """``fn(*args)`` in a worker (``run_plan`` in the service) for map ``key``; ``Unavailable`` when too
        busy, or when its worker was stuck (ended and replaced) or crashed."""
        worker = await self._acquire(key)
        loop = asyncio.get_running_loop()
        future: concurrent.futures.Future[T] | None = None
        try:
            for attempt in (1, 2):
                try:
                    future = await loop.run_in_executor(None, self._submit, worker, fn, *args)
                    break
                except BrokenProcessPool:
                    # the worker died while idle (the OOM killer, a kill): this plan has not run, so it
                    # may go to a new process; without this, every later plan would fail the same way
                    LOG.error("a planner worker had died; starting a new one",
                              extra={"fields": {"worker": worker.index}})
                    worker.end()
                    if attempt == 2:
                        raise Unavailable("the planner workers stopped unexpectedly; retry") from None
            try:
                return await asyncio.wait_for(asyncio.wrap_future(future), timeout_s)
            except TimeoutError:
                LOG.error("planner worker did not answer in %.1f s; ending it and starting a new one", timeout_s,
                          extra={"fields": {"worker": worker.index, "map": key}})
                worker.end()
                raise Unavailable(f"the planner did not finish within {timeout_s:.1f} s; retry") from None
            except BrokenProcessPool:
                LOG.error("a planner worker died; starting a new one", extra={"fields": {"worker": worker.index}})
                worker.end()
                raise Unavailable("the planner worker stopped unexpectedly; retry") from None
        finally:
            worker.last_key = key
            if future is not None and not future.done() and worker.executor is not None:
                # the request went away (cancelled) while its worker still solves: the worker is free only
                # when that solve ends, or the next plan would wait behind it on the next plan's clock
                future.add_done_callback(lambda _: loop.call_soon_threadsafe(self._release, worker, key))
            else:
                self._release(worker, key)

    def shutdown(self) -> None:
        """Stop the workers: idle ones at once, one still busy (a plan whose request the graceful shutdown
        gave up on, or a warm-up) after ``SHUTDOWN_GRACE_S``, so that a stop fits ``docker stop``'s time."""
        if self._warming is not None:
            self._warming.cancel()
        processes = [p for w in self._workers for p in w.processes()]
        for worker in self._workers:
            executor, worker.executor = worker.executor, None
            if executor is not None:
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
