"""The threads a cast's walks and a fusion's writes run on: compiled kernels that release the GIL, split so that the
result does not depend on the split (every split gives the same map, bit for bit).

``set_threads`` chooses how many (the service sets it from its configuration); by default one per CPU this process
may run on. Work below ``MIN_PER_THREAD`` items a thread is not split: handing it to a thread costs more than it saves.
The parts run at the priority of the thread that splits them (a pool per nice value): a fusion a service runs at a
lower priority so that it takes only the CPU others leave must not get its parts back at full priority.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: Rays (or cells) a thread must get before work is split between threads.
MIN_PER_THREAD = 8192

_lock = threading.Lock()


def _cpus() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


_threads = _cpus()
_pools: dict[int | None, ThreadPoolExecutor] = {}


def set_threads(n: int | None) -> None:
    """Split work between at most ``n`` threads (1: never split; None: one per CPU this process may run on)."""
    global _threads
    if n is not None and int(n) < 1:
        raise ValueError(f"threads must be at least 1, got {n}")
    with _lock:
        _threads = _cpus() if n is None else int(n)
        for pool in _pools.values():
            pool.shutdown(wait=False)
        _pools.clear()


def threads() -> int:
    """The most threads work is split between."""
    return _threads


def walks_for(items: int) -> int:
    """How many parts to split ``items`` rays or cells into."""
    return max(1, min(_threads, items // MIN_PER_THREAD))


def run(fn: Callable[[T], R], parts: Iterable[T]) -> list[R]:
    """``[fn(p) for p in parts]``, the first in the calling thread and the others in the pool, side by side."""
    parts = list(parts)
    if len(parts) <= 1:
        return [fn(p) for p in parts]
    nice = _nice()
    with _lock:
        pool = _pools.get(nice)
        if pool is None:
            pool = _pools[nice] = ThreadPoolExecutor(max_workers=max(1, _threads - 1), thread_name_prefix="fuzzyocc",
                                                     initializer=_set_nice, initargs=(nice,))
    others = [pool.submit(fn, p) for p in parts[1:]]
    first = fn(parts[0])
    return [first, *(f.result() for f in others)]


def beside(name: str) -> ThreadPoolExecutor:
    """One thread of its own at the calling thread's priority, for work that runs beside the caller's and may split
    itself (:func:`run`): not one of the pool's, whose parts would then wait behind it. The caller shuts it down."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix=name, initializer=_set_nice, initargs=(_nice(),))


def _nice() -> int | None:
    """The calling thread's nice value (Linux: a thread's own), None where there is none to read."""
    try:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    except (AttributeError, OSError):
        return None


def _set_nice(nice: int | None) -> None:
    if nice is not None:
        with contextlib.suppress(OSError):  # raising a priority needs a privilege: the part then runs as it can
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
