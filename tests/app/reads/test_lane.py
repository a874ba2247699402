"""The big reads' lane (bench abuse row 10): one at a time, a rest after each, a bounded queue."""

from __future__ import annotations

import asyncio
import time

import pytest

from app.errors import Unavailable
from app.reads.lane import ReadLane


def test_the_next_big_read_starts_after_a_rest_in_proportion_to_the_last() -> None:
    async def scenario() -> tuple[float, float, float]:
        lane = ReadLane(share=0.25, queue=4)  # rest: 3 x the work
        starts: list[float] = []

        async def read(seconds: float) -> None:
            async with lane.turn():
                starts.append(time.monotonic())
                await asyncio.sleep(seconds)

        began = time.monotonic()
        await read(0.1)  # alone: not delayed
        ended = time.monotonic()
        await asyncio.gather(read(0.1), read(0.0))
        return starts[0] - began, starts[1] - ended, starts[2] - starts[1]

    first_wait, second_wait, third_wait = asyncio.run(scenario())
    assert first_wait < 0.05
    assert second_wait >= 0.29  # 3 x 0.1 s of rest after the first read
    assert third_wait >= 0.1 + 0.29  # the second's work, then its rest


async def _one_holding_one_waiting(lane: ReadLane, release: asyncio.Event) -> tuple[asyncio.Future[None], ...]:
    """A read holding the lane until ``release``, and one waiting for its turn."""

    async def read() -> None:
        async with lane.turn():
            await release.wait()

    holder = asyncio.ensure_future(read())
    await asyncio.sleep(0.01)
    waiter = asyncio.ensure_future(read())
    await asyncio.sleep(0.01)
    return holder, waiter


def test_reads_beyond_the_queue_are_refused_and_name_the_setting() -> None:
    async def scenario() -> None:
        lane = ReadLane(share=1.0, queue=1)
        release = asyncio.Event()
        holder, waiter = await _one_holding_one_waiting(lane, release)
        assert lane.waiting == 1
        with pytest.raises(Unavailable, match="FUZZYRISK_HEAVY_READ_QUEUE") as refused:
            async with lane.turn():
                pass
        assert refused.value.headers == {"Retry-After": "1"}
        release.set()
        await asyncio.gather(holder, waiter)
        assert lane.waiting == 0

    asyncio.run(scenario())


def test_a_cancelled_wait_gives_its_place_back() -> None:
    async def scenario() -> None:
        lane = ReadLane(share=1.0, queue=1)
        release = asyncio.Event()
        holder, gone = await _one_holding_one_waiting(lane, release)
        gone.cancel()  # the client went away while it waited
        await asyncio.sleep(0.01)
        assert lane.waiting == 0
        release.set()
        await holder
        async with lane.turn():  # the lane is free again (share 1: no rest)
            pass

    asyncio.run(scenario())


@pytest.mark.parametrize("share", [0.0, -0.5, 1.5])
def test_a_share_outside_zero_to_one_is_refused(share: float) -> None:
    with pytest.raises(ValueError, match="share"):
        ReadLane(share=share, queue=1)


def test_a_turn_handed_over_lasts_until_its_body_is_sent(monkeypatch: pytest.MonkeyPatch) -> None:
    # the body of a big read (16 MB of OccupancyGrid) is part of its work: with renders four times faster and the
    # turn ending at the render, the lane let four times as many bodies out (bench abuse row 10)
    from app.reads import lane as readlane

    monkeypatch.setattr(readlane, "MAX_SEND_HELD_S", 0.5)

    async def scenario() -> tuple[float, float]:
        lane = ReadLane(share=1.0, queue=4)
        async with lane.turn() as turn:
            sent = turn.hand_over()
        began = time.monotonic()
        loop = asyncio.get_running_loop()
        loop.call_later(0.2, sent)  # the response's last byte, 0.2 s later
        async with lane.turn() as second:
            waited = time.monotonic() - began
            second.hand_over()  # and never sent (a client reading slowly): the lane goes on after MAX_SEND_HELD_S
        began = time.monotonic()
        async with lane.turn():
            waited_for_lost = time.monotonic() - began
        return waited, waited_for_lost

    waited, waited_for_lost = asyncio.run(scenario())
    assert 0.18 <= waited < 0.4
    assert 0.45 <= waited_for_lost < 1.0


def test_the_rest_after_a_long_turn_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    # a read that waited seconds for its map's batch before its copy must not close the lane for three times that
    from app.reads import lane as readlane

    monkeypatch.setattr(readlane, "MAX_REST_S", 0.3)

    async def scenario() -> float:
        lane = ReadLane(share=0.25, queue=4)
        async with lane.turn():
            await asyncio.sleep(0.4)  # rest 3 x 0.4 s, bounded to 0.3 s
        began = time.monotonic()
        async with lane.turn():
            return time.monotonic() - began

    assert 0.28 <= asyncio.run(scenario()) < 0.6
