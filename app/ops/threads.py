"""The service's thread pools: fusion (light and heavy batches apart), parsing and reads, each with its own threads.

Parsing has its own threads so that a burst of queued batches cannot put its parsing ahead of
the commit and fusion of the batch whose turn it is, nor ahead of readers' copies; reads have
theirs so that a read of one map never waits behind minutes of fusion of others.
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from app.ops import process_setup

T = TypeVar("T")


class Workers:
    """``run`` (fusion, snapshots, storage), ``run_parser`` (bodies) and ``run_read`` (copies, encodings)."""

    def __init__(self, *, fusion_threads: int, read_threads: int) -> None:
        self._fusion = ThreadPoolExecutor(fusion_threads, thread_name_prefix="fusion")
        self._heavy = ThreadPoolExecutor(fusion_threads, thread_name_prefix="fusion-heavy", initializer=_yield_cpu)
        self._parsers = ThreadPoolExecutor(fusion_threads, thread_name_prefix="parse")
        self._admin = ThreadPoolExecutor(1, thread_name_prefix="admin")
        self._readers = ThreadPoolExecutor(read_threads, thread_name_prefix="read")
        # one: big reads take turns (``app.reads.lane``)
        self._heavy_readers = ThreadPoolExecutor(1, thread_name_prefix="read-heavy", initializer=_yield_cpu)
        self._started: dict[int, float] = {}  # fusion jobs running: id -> time.monotonic() at their start
        self._ids = itertools.count()

    async def run(self, fn: Callable[..., T], *args: object) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._fusion, self._timed, fn, args)

    async def run_heavy(self, fn: Callable[..., T], *args: object) -> T:
        """``run`` for a heavy batch (``writepath.HEAVY_BATCH_CELLS``): it never takes the threads of the others."""
        return await asyncio.get_running_loop().run_in_executor(self._heavy, self._timed, fn, args)

    def _timed(self, fn: Callable[..., T], args: tuple[object, ...]) -> T:
        job = next(self._ids)
        self._started[job] = time.monotonic()
        try:
            return fn(*args)
        finally:
            del self._started[job]

    def longest_fusion_job_s(self) -> float:
        """How long the oldest job now in a fusion thread (a batch, a snapshot, a load) has run; 0 when idle."""
        started = tuple(self._started.values())  # one C-level copy: the threads add and remove meanwhile
        return time.monotonic() - min(started) if started else 0.0

    async def run_admin(self, fn: Callable[..., T], *args: object) -> T:
        """Making and deleting maps (their arrays, their rows), giving freed memory back: one thread of its own, so
        that a client making and deleting maps in a loop never holds the threads other maps' batches fuse in."""
        return await asyncio.get_running_loop().run_in_executor(self._admin, fn, *args)

    async def run_parser(self, fn: Callable[..., T], *args: object) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._parsers, fn, *args)

    async def run_read(self, fn: Callable[..., T], *args: object, heavy: bool = False) -> T:
        """A read; ``heavy`` (a grid of more than ``reads.HEAVY_READ_CELLS``) in threads of its own, at a lower
        priority, so that big reads never hold every read thread."""
        pool = self._heavy_readers if heavy else self._readers
        return await asyncio.get_running_loop().run_in_executor(pool, fn, *args)

    def shutdown(self) -> None:
        """Wait for the work under way (grids being written included), then release the threads."""
        self._parsers.shutdown(wait=True)
        self._admin.shutdown(wait=True)
        self._readers.shutdown(wait=True)
        self._heavy_readers.shutdown(wait=True)
        self._heavy.shutdown(wait=True)
        self._fusion.shutdown(wait=True)


#: How much nicer than the server the heavy batches' threads run (Linux schedules each thread with its own).
HEAVY_NICE = 10


def _yield_cpu() -> None:
    """Run this thread (a heavy batch's, a heavy read's) at a lower priority: it takes the CPU a robot's batch or
    read leaves, not a share of it (two 2 M-beam scans at equal priority took two thirds of the 2 cores from every
    other map's fusion)."""
    process_setup.lower_priority(HEAVY_NICE)
