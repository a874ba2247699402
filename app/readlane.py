"""Reads of big grids take turns in one lane, which rests after each in proportion to its work.

A read of a big map (``reads.HEAVY_READ_CELLS``) copies the grid (a 16 M-cell map: 80 MB of risk and
observed mask) and renders it (about 0.16 s of a core for an OccupancyGrid). Read side by side, such
reads held a copy each while they waited for their render, and took both cores from every other
client: two readers of a 16 M-cell OccupancyGrid, back to back, made an innocent client's scans 2.6x
slower at the 99th percentile (issue 11, bench abuse row 10). In the lane a big read holds its turn from
its copy to the end of its render; the lane then stays closed ``busy x (1 / share - 1)`` seconds, so that
big reads together take at most ``share`` of one core and hold one copy. A read alone is not delayed
(the rest comes after it); reads waiting beyond ``queue`` are refused with 503.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator

from app.errors import Unavailable


class ReadLane:
    """One big read at a time, then a rest; ``queue`` more may wait for their turn."""

    def __init__(self, *, share: float, queue: int) -> None:
        if not 0.0 < share <= 1.0:
            raise ValueError(f"share must be in (0, 1], got {share}")
        self._rest_per_busy = 1.0 / share - 1.0
        self._queue = queue
        self._lock = asyncio.Lock()  # FIFO: turns are taken in arrival order
        self._waiting = 0

    @property
    def waiting(self) -> int:
        """Big reads waiting for their turn."""
        return self._waiting

    @contextlib.asynccontextmanager
    async def turn(self) -> AsyncIterator[None]:
        """Hold the lane for the block; its rest starts when the block ends (this caller does not wait for it)."""
        if self._waiting >= self._queue:
            raise Unavailable(
                f"{self._waiting} reads of big maps are waiting for their turn already; retry shortly "
                "(FUZZYRISK_HEAVY_READ_QUEUE, FUZZYRISK_HEAVY_READ_SHARE)",
                headers={"Retry-After": "1"},
            )
        self._waiting += 1
        try:
            await self._lock.acquire()
        finally:
            self._waiting -= 1
        started = time.monotonic()
        try:
            yield
        finally:
            rest = (time.monotonic() - started) * self._rest_per_busy
            asyncio.get_running_loop().call_later(rest, self._lock.release)
