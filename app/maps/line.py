"""A map's writers: one at a time in arrival order through its line, each write run to its end once it has its place.

``Turns`` and ``Line`` order the writers of one map (``MapEntry.line``); ``shielded`` keeps a write going
when its request is cancelled (a client gone away), so that it still leaves its place in line and its rows whole.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")


class Turns:
    """Tickets handed out in arrival order; holders pass one at a time, in ticket order.

    ``take`` is synchronous, so calling it before the first ``await`` of a request fixes the
    request's place in line. Every ticket taken must be ``done`` exactly once (``finally``),
    whether its holder ran, failed or was cancelled, or the line stops.
    """

    def __init__(self) -> None:
        self._next = 0
        self._serving = 0
        self._finished: set[int] = set()
        self._waiters: dict[int, asyncio.Future[None]] = {}

    def take(self) -> int:
        ticket = self._next
        self._next += 1
        return ticket

    @property
    def outstanding(self) -> int:
        """Tickets taken and not yet done."""
        return self._next - self._serving - len(self._finished)

    async def wait(self, ticket: int) -> None:
        """Return once every earlier ticket is done."""
        if ticket == self._serving:
            return
        waiter = asyncio.get_running_loop().create_future()
        self._waiters[ticket] = waiter
        try:
            await waiter
        finally:
            del self._waiters[ticket]

    def done(self, ticket: int) -> None:
        """Give the turn up (a ticket finished early, e.g. a refused batch, is skipped when its turn comes).

        Idempotent: a ticket given up again is ignored.
        """
        if ticket < self._serving or ticket in self._finished:
            return
        self._finished.add(ticket)
        while self._serving in self._finished:
            self._finished.discard(self._serving)
            self._serving += 1
        waiter = self._waiters.get(self._serving)
        if waiter is not None and not waiter.done():
            waiter.set_result(None)


class Line:
    """A map's writers in arrival order through two stages, each passed in ticket order: commit, then apply.

    A ticket enters a stage once every earlier ticket has left it. A batch leaves the commit
    stage as soon as it is durable, so the next batch's fsync overlaps this one's fusion.
    ``done`` leaves both stages (``finally``: whatever happened to the holder).
    """

    def __init__(self) -> None:
        self.commit = Turns()
        self.apply = Turns()

    @property
    def outstanding(self) -> int:
        """Holders in line: taken, not yet out of the apply stage."""
        return self.apply.outstanding

    def take(self) -> int:
        ticket = self.commit.take()
        if self.apply.take() != ticket:  # both are only ever taken here, together
            raise RuntimeError("commit and apply tickets out of step")
        return ticket

    async def wait_all(self, ticket: int) -> None:
        """Return once every earlier ticket has left both stages (the map is this holder's alone)."""
        await self.commit.wait(ticket)
        await self.apply.wait(ticket)

    def done(self, ticket: int) -> None:
        self.commit.done(ticket)
        self.apply.done(ticket)


async def shielded(work: Coroutine[Any, Any, T]) -> T:
    """Run ``work`` to its end even if the awaiting request is cancelled (a client gone away)."""
    task = asyncio.ensure_future(work)
    task.add_done_callback(_retrieve)
    return await asyncio.shield(task)


def _retrieve(task: asyncio.Future[Any]) -> None:
    """Mark a shielded task's exception as seen: its request may have been cancelled, and the error
    reached the client (or nobody) through the shield, not through this task."""
    if not task.cancelled():
        task.exception()
