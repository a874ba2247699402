"""The planner worker pool: a stuck or dead worker answers 503 and is replaced; a full queue answers 503."""

from __future__ import annotations

import asyncio
import math
import os
import time

import pytest

from app.errors import Unavailable
from app.planworker import PlanPool


def test_a_stuck_worker_is_ended_and_replaced() -> None:
    async def scenario() -> None:
        pool = PlanPool(workers=1, queue=1)
        try:
            with pytest.raises(Unavailable, match="did not finish"):
                await pool.run(time.sleep, 0.5, 60)  # a solve that never returns
            assert await pool.run(math.sqrt, 30.0, 16.0) == 4.0
        finally:
            pool.shutdown()

    asyncio.run(scenario())


def test_a_crashed_worker_is_replaced() -> None:
    async def scenario() -> None:
        pool = PlanPool(workers=1, queue=1)
        try:
            with pytest.raises(Unavailable, match="stopped unexpectedly"):
                await pool.run(os._exit, 30.0, 3)  # as a segfault in OMPL would
            assert await pool.run(math.sqrt, 30.0, 9.0) == 3.0
        finally:
            pool.shutdown()

    asyncio.run(scenario())


def test_plans_beyond_workers_and_queue_are_refused_at_once() -> None:
    async def scenario() -> None:
        pool = PlanPool(workers=1, queue=1)
        try:
            running = asyncio.ensure_future(pool.run(time.sleep, 30.0, 1.0))
            waiting = asyncio.ensure_future(pool.run(time.sleep, 30.0, 0.0))
            await asyncio.sleep(0.05)
            with pytest.raises(Unavailable) as refused:
                await pool.run(math.sqrt, 30.0, 1.0)
            assert refused.value.headers == {"Retry-After": "1"}
            await asyncio.gather(running, waiting)
            assert await pool.run(math.sqrt, 30.0, 1.0) == 1.0  # room again
        finally:
            pool.shutdown()

    asyncio.run(scenario())
