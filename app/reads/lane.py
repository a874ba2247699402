"""Reads of big grids take turns in one lane, which rests after each in proportion to its work.

A read of a big map (``reads.HEAVY_READ_CELLS``) copies or renders the grid and sends a body of up to
tens of MB. Read side by side, such reads held a copy each while they waited for their render, and
took both cores from every other client: two readers of a 16 M-cell OccupancyGrid, back to back, made
an innocent client's scans 2.6x slower at the 99th percentile (bench abuse row 10). In the
lane a big read holds its turn from its copy until its last byte is sent (``Turn.hand_over``: the
response ends it), at most ``MAX_SEND_HELD_S`` of the sending; the lane then stays closed
``busy x (1 / share - 1)`` seconds, at most ``MAX_REST_S``, so that big reads together take about
``share`` of the time and hold one copy. The bounds keep a slow client, or a read that waited for its
map's batch, from closing the lane for long. A read that finds the lane idle is not delayed (the rest
comes after it); reads waiting beyond ``queue`` are refused with 503.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable

from app.errors import Unavailable

#: Longest a turn handed over to a response is held while its body is sent: sending costs the server (and a client
#: on the same computer) as much as the render, but a client reading slowly must not hold the lane.
MAX_SEND_HELD_S = 0.5
#: Longest rest after a turn (a read that waited seconds for its map's batch before its copy counts that time).
MAX_REST_S = 2.0


class Turn:
    """A big read's turn in the lane: ended once (``end``), by the read or, handed over, by its response."""

    def __init__(self, lane: ReadLane) -> None:
        self._lane = lane
        self._started = time.monotonic()
        self._ended = False
        self._handed_over = False
        self._timer: asyncio.TimerHandle | None = None

    def hand_over(self) -> Callable[[], None]:
        """Leave the end to the caller (a response, once its last byte is sent; ``MAX_SEND_HELD_S`` at most): the
        function that ends it."""
        self._handed_over = True
        self._timer = asyncio.get_running_loop().call_later(MAX_SEND_HELD_S, self.end)
        return self.end

    def end(self) -> None:
        """End the turn (again: nothing); the lane rests in proportion to how long it was held."""
        if self._ended:
            return
        self._ended = True
        if self._timer is not None:
            self._timer.cancel()
        self._lane.rest(min(MAX_REST_S, (time.monotonic() - self._started) * self._lane.rest_per_busy))


class ReadLane:
    """One big read at a time, then a rest; ``queue`` more may wait for their turn."""

    def __init__(self, *, share: float, queue: int) -> None:
        if not 0.0 < share <= 1.0:
            raise ValueError(f"share must be in (0, 1], got {share}")
        self.rest_per_busy = 1.0 / share - 1.0
        self._queue = queue
        self._lock = asyncio.Lock()  # FIFO: turns are taken in arrival order
        self._waiting = 0

    @property
    def waiting(self) -> int:
        """Big reads waiting for their turn."""
        return self._waiting

    @contextlib.asynccontextmanager
    async def turn(self) -> AsyncIterator[Turn]:
        """Hold the lane for the block, or longer when the block hands the turn over (``Turn.hand_over``)."""
        if self._waiting >= self._queue:
            raise Unavailable(
                f"{self._waiting} reads of big maps (their grids, or copies of them for plans) are waiting for "
                "their turn already; retry shortly (FUZZYRISK_HEAVY_READ_QUEUE, FUZZYRISK_HEAVY_READ_SHARE)",
                headers={"Retry-After": "1"},
            )
        self._waiting += 1
        try:
            await self._lock.acquire()
        finally:
            self._waiting -= 1
        held = Turn(self)
        try:
            yield held
        except BaseException:
            held.end()
            raise
        if not held._handed_over:
            held.end()

    def rest(self, seconds: float) -> None:
        """Open the lane to the next turn in ``seconds``."""
        asyncio.get_running_loop().call_later(seconds, self._lock.release)
