"""The planner worker pool: a stuck or dead worker answers 503 and is replaced alone; a full queue answers 503;
waiting plans take turns by map."""

from __future__ import annotations

import asyncio
import math
import os
import signal
import time

import numpy as np
import pytest

from app.errors import Unavailable
from app.plans import pool as planworker
from app.plans.pool import PlanPool


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


def test_a_worker_that_died_while_idle_is_replaced_for_the_next_task() -> None:
    async def scenario() -> None:
        pool = PlanPool(workers=1, queue=1)
        try:
            pid = await pool.run(os.getpid, 30.0)
            os.kill(pid, signal.SIGKILL)  # the OOM killer, between two plans
            for _ in range(100):  # until the pool has noticed (it is then broken for every later task)
                executor = pool._workers[0].executor
                if executor is not None and executor._broken:  # type: ignore[attr-defined]
                    break
                await asyncio.sleep(0.05)
            assert await pool.run(math.sqrt, 30.0, 25.0) == 5.0  # this task had not run: it goes to a new worker
            assert await pool.run(os.getpid, 30.0) != pid
        finally:
            pool.shutdown()

    asyncio.run(scenario())


@pytest.fixture
def short_room_wait(monkeypatch: pytest.MonkeyPatch) -> float:
    """Plans finding the queue full wait 0.2 s for room (not ``ROOM_WAIT_S``), for the tests of refusals."""
    monkeypatch.setattr(planworker, "ROOM_WAIT_S", 0.2)
    return 0.2


def test_plans_beyond_workers_and_queue_are_refused_after_the_wait_for_room() -> None:
    async def scenario() -> float:
        pool = PlanPool(workers=1, queue=1)
        try:
            running = asyncio.ensure_future(pool.run(time.sleep, 30.0, 3.0))
            waiting = asyncio.ensure_future(pool.run(time.sleep, 30.0, 0.0))
            await asyncio.sleep(0.05)
            started = time.monotonic()
            with pytest.raises(Unavailable) as refused:
                await pool.run(math.sqrt, 30.0, 1.0)
            waited = time.monotonic() - started
            assert refused.value.headers == {"Retry-After": "1"}
            await asyncio.gather(running, waiting)
            assert await pool.run(math.sqrt, 30.0, 1.0) == 1.0  # room again
            return waited
        finally:
            pool.shutdown()

    # bench abuse row 9: answered at once, ten clients that ignored Retry-After asked 90 times a second
    assert planworker.ROOM_WAIT_S - 0.05 <= asyncio.run(scenario()) < 2.5


def test_a_plan_that_finds_the_queue_full_joins_it_when_room_comes_within_the_wait() -> None:
    async def scenario() -> float:
        pool = PlanPool(workers=1, queue=1)
        try:
            await pool.run(os.getpid, 30.0)  # the worker is up
            running = asyncio.ensure_future(pool.run(time.sleep, 30.0, 0.4))
            await asyncio.sleep(0.05)
            waiting = asyncio.ensure_future(pool.run(math.sqrt, 30.0, 4.0))
            await asyncio.sleep(0.05)
            assert await pool.run(math.sqrt, 30.0, 9.0) == 3.0  # room came as the first plan ended
            assert await waiting == 2.0
            await running
            return pool.waiting
        finally:
            pool.shutdown()

    assert asyncio.run(scenario()) == 0


def test_a_stuck_worker_is_replaced_alone_and_the_other_plan_goes_on() -> None:
    async def scenario() -> None:
        pool = PlanPool(workers=2, queue=2)
        try:
            other_pid = await pool.run(os.getpid, 30.0, key="b")
            stuck = asyncio.ensure_future(pool.run(time.sleep, 1.0, 60, key="a"))  # takes the other worker
            await asyncio.sleep(0.1)
            other = asyncio.ensure_future(pool.run(_sleep_then_pid, 30.0, 2.0, key="b"))
            with pytest.raises(Unavailable, match="did not finish"):
                await stuck
            assert await other == other_pid  # the stuck worker's end did not touch it
            assert await pool.run(math.sqrt, 30.0, 4.0, key="a") == 2.0
        finally:
            pool.shutdown()

    asyncio.run(scenario())


def _sleep_then_pid(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def test_a_cancelled_plan_frees_its_worker_only_when_its_solve_ends() -> None:
    # the request of a long plan goes away; the next plan (another map) must not wait behind the
    # abandoned solve on its own clock, nor have the worker ended under it
    async def scenario() -> None:
        pool = PlanPool(workers=1, queue=2)
        try:
            pid = await pool.run(os.getpid, 30.0, key="a")
            abandoned = asyncio.ensure_future(pool.run(time.sleep, 30.0, 2.5, key="a"))
            await asyncio.sleep(0.3)
            abandoned.cancel()
            started = time.monotonic()
            # it waits for the abandoned solve (2.2 s more), then runs on its own 1 s clock, on the same process
            assert await pool.run(os.getpid, 1.0, key="b") == pid
            assert time.monotonic() - started >= 2.0
        finally:
            pool.shutdown()

    asyncio.run(scenario())


def test_waiting_plans_take_turns_by_map() -> None:
    async def scenario() -> list[str]:
        pool = PlanPool(workers=1, queue=8)
        order: list[str] = []

        async def plan(key: str, tag: str) -> None:
            order.append(await pool.run(str, 30.0, tag, key=key))

        try:
            busy = asyncio.ensure_future(pool.run(time.sleep, 30.0, 0.5, key="a"))
            await asyncio.sleep(0.05)
            waiting = [asyncio.ensure_future(plan(key, tag)) for key, tag in
                       [("a", "a1"), ("a", "a2"), ("a", "a3"), ("b", "b1")]]
            await asyncio.gather(busy, *waiting)
        finally:
            pool.shutdown()
        return order

    assert asyncio.run(scenario()) == ["a1", "b1", "a2", "a3"]  # b's plan does not wait for all of a's


def test_one_map_holds_at_most_half_the_queue(short_room_wait: float) -> None:
    async def scenario() -> None:
        pool = PlanPool(workers=1, queue=4)
        try:
            busy = asyncio.ensure_future(pool.run(time.sleep, 30.0, 0.5, key="a"))
            await asyncio.sleep(0.05)
            queued = [asyncio.ensure_future(pool.run(math.sqrt, 30.0, 1.0, key="a")) for _ in range(2)]
            await asyncio.sleep(0.05)
            with pytest.raises(Unavailable, match="2 of them on this map"):
                await pool.run(math.sqrt, 30.0, 1.0, key="a")
            assert await pool.run(math.sqrt, 30.0, 9.0, key="b") == 3.0  # another map still gets in
            await asyncio.gather(busy, *queued)
        finally:
            pool.shutdown()

    asyncio.run(scenario())


def test_a_map_flooded_with_plans_leaves_a_worker_to_the_others() -> None:
    # bench abuse row 9: ten clients' plans on one map held both workers, so another map's plan
    # waited for one of its solves, and both cores solved while the innocent's scans waited for CPU
    async def scenario() -> None:
        pool = PlanPool(workers=2, queue=8)
        try:
            await asyncio.gather(pool.run(os.getpid, 30.0, key="a"), pool.run(os.getpid, 30.0, key="b"))  # both up
            flood = [asyncio.ensure_future(pool.run(_sleep_then_pid, 30.0, 0.6, key="a")) for _ in range(3)]
            await asyncio.sleep(0.3)
            started = time.monotonic()
            other = await pool.run(os.getpid, 30.0, key="b")
            assert time.monotonic() - started < 0.3  # a free worker, not the end of one of a's solves
            pids = await asyncio.gather(*flood)
            assert other not in pids  # a's three plans ran one after the other on one worker
            assert len(set(pids)) == 1
        finally:
            pool.shutdown()

    asyncio.run(scenario())


def test_a_plan_waiting_for_room_takes_a_worker_that_comes_free_for_it() -> None:
    # the queue stays full (map a's plan waits, a at its share of the workers); a worker freed by map b is c's
    async def scenario() -> float:
        pool = PlanPool(workers=2, queue=1)
        try:
            await asyncio.gather(pool.run(os.getpid, 30.0, key="a"), pool.run(os.getpid, 30.0, key="b"))  # both up
            a_running = asyncio.ensure_future(pool.run(time.sleep, 30.0, 2.0, key="a"))
            b_running = asyncio.ensure_future(pool.run(time.sleep, 30.0, 0.3, key="b"))
            await asyncio.sleep(0.1)
            a_waiting = asyncio.ensure_future(pool.run(math.sqrt, 30.0, 1.0, key="a"))  # the whole queue
            await asyncio.sleep(0.05)
            started = time.monotonic()
            assert await pool.run(math.sqrt, 30.0, 4.0, key="c") == 2.0  # before: 503 after ROOM_WAIT_S
            took = time.monotonic() - started
            await asyncio.gather(a_running, b_running, a_waiting)
            return took
        finally:
            pool.shutdown()

    assert asyncio.run(scenario()) < planworker.ROOM_WAIT_S


def test_a_map_may_hold_every_worker_when_configured() -> None:
    async def scenario() -> float:
        pool = PlanPool(workers=2, queue=8, per_map=2)
        try:
            await asyncio.gather(*(pool.run(os.getpid, 30.0, key="a") for _ in range(2)))  # both started
            started = time.monotonic()
            await asyncio.gather(*(pool.run(time.sleep, 30.0, 0.5, key="a") for _ in range(2)))
            return time.monotonic() - started
        finally:
            pool.shutdown()

    assert asyncio.run(scenario()) < 0.9  # side by side, not one after the other


def test_a_refusal_names_the_per_map_setting(short_room_wait: float) -> None:
    async def scenario() -> None:
        pool = PlanPool(workers=2, queue=2)
        try:
            busy = [asyncio.ensure_future(pool.run(time.sleep, 30.0, 0.4, key="a")) for _ in range(2)]
            await asyncio.sleep(0.1)  # one running, one waiting (its share of the queue)
            with pytest.raises(Unavailable, match="may hold 1 of the 2 workers") as refused:
                await pool.run(math.sqrt, 30.0, 1.0, key="a")
            assert "FUZZYRISK_PLAN_WORKERS_PER_MAP" in str(refused.value)
            await asyncio.gather(*busy)
        finally:
            pool.shutdown()

    asyncio.run(scenario())


@pytest.mark.parametrize("native", [True, False])
def test_workers_use_the_compiled_planner_callbacks_unless_configured_not_to(native: bool) -> None:
    from planning import native as compiled

    from app.plans.worker import run_plan

    risk = np.zeros((40, 40), np.float32)
    params = {"start": [0.3, 0.3], "goal": [1.7, 1.7], "planner": "RRTstar", "time_limit": 0.2, "seed": 1}

    async def scenario() -> dict[str, str]:
        pool = PlanPool(workers=1, queue=1, native=native)
        try:
            answer = await pool.run(run_plan, 30.0, risk, np.ones_like(risk, bool), 0.05, (0.0, 0.0), params)
            assert answer["result"]["status"] == "exact", answer
            return await pool.run(compiled.status, 30.0)  # the same (only) worker, after its plan
        finally:
            pool.shutdown()

    status = asyncio.run(scenario())
    if native:  # the worker's warm-up checked every space the compiled callbacks cover
        assert status == {f"{kind} {space}": "native" for kind in compiled.KINDS for space in compiled.SPACES}
    else:
        assert status == {}  # never tried


def _niceness() -> int:
    return os.getpriority(os.PRIO_PROCESS, 0)


def test_plans_run_at_a_lower_priority_than_the_server() -> None:
    # bench abuse rows 7 and 9: a 30 s plan, and ten clients' plans on both cores, made an innocent
    # client's map reads 2.6x slower; a plan now takes the CPU that scans and reads leave
    async def scenario() -> int:
        pool = PlanPool(workers=1, queue=1)
        try:
            return await pool.run(_niceness, 30.0)
        finally:
            pool.shutdown()

    assert asyncio.run(scenario()) > _niceness()
