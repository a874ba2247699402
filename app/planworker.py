"""What runs inside a planner worker process, and the pool that runs it.

OMPL's ``solve()`` holds the GIL for the whole solve, so plans never run on the
event loop's process: a bounded ``ProcessPoolExecutor`` (forkserver, or spawn where
there is no forkserver) receives the risk grid and the parameters, and returns
plain data. Workers import ``planning`` (and OMPL) once, at start.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import multiprocessing
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

import numpy as np

from app.errors import Unavailable

LOG = logging.getLogger("fuzzyrisk.plans")
T = TypeVar("T")


def _init_worker(native: bool) -> None:
    """In each new worker: use the compiled planner callbacks (``planning/native.py``) or not, and
    compile or load every kernel now, so that no plan waits for it."""
    import planning
    from planning import native as compiled

    # OMPL's plain-text warnings would break the service's one-JSON-object-a-line logs; what they
    # warn about comes back in each result (status, message) or is documented (planning/README.md)
    planning.quiet_ompl()
    compiled.set_enabled(native)
    planning.warm_up()  # its plans load (or compile) the compiled callbacks too


def _warm() -> None:
    """Start a worker (its initializer warms the planner stack up) so the first plan does not pay for it."""


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
    from planning import PlanError, RiskField, plan

    try:
        field = RiskField(risk, resolution, origin, observed=observed)
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
        }
    }


def _context() -> multiprocessing.context.BaseContext:
    # fork would copy the server's threads and locks into the child; forkserver forks a clean
    # process that has already imported the planner stack
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    context = multiprocessing.get_context(method)
    if method == "forkserver":
        context.set_forkserver_preload(["app.planworker", "planning"])
    return context


class PlanPool:
    """At most ``workers`` plans run at once; up to ``queue`` more wait; beyond that, 503."""

    def __init__(self, *, workers: int, queue: int, native: bool = True) -> None:
        self._workers = workers
        self._queue = queue
        self._native = native
        self._waiting = 0
        self._running = asyncio.Semaphore(workers)
        self._executor: concurrent.futures.ProcessPoolExecutor | None = None
        self._warming: asyncio.Future[Any] | None = None

    def start(self) -> None:
        """Start the worker processes in the background (otherwise they start at the first plan)."""
        executor = self._ensure()
        # submit() starts processes, and the first one waits for the forkserver to import the
        # planner stack (seconds): never on the event loop
        self._warming = asyncio.get_running_loop().run_in_executor(
            None, lambda: [executor.submit(_warm) for _ in range(self._workers)]
        )

    def _ensure(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._executor is None:
            # creating the executor starts no process; submit() does
            self._executor = concurrent.futures.ProcessPoolExecutor(
                self._workers, mp_context=_context(), initializer=_init_worker, initargs=(self._native,)
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
                executor = self._ensure()
                loop = asyncio.get_running_loop()
                future = await loop.run_in_executor(None, lambda: executor.submit(fn, *args))
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
        """Stop the workers (plans in flight were awaited by the server before this)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
