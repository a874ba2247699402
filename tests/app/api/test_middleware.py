"""Guards: the API key, the body limits enforced while reading, the budget of bodies in flight, the caps on
maps, and answers that do not echo huge inputs."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from starlette.middleware.exceptions import ExceptionMiddleware

from app.config import Settings
from app.api.middleware import BodyBudgetMiddleware
from tests.conftest import error_message

KEY = "s3cret-key-for-tests-0123456789"


@pytest.fixture
def locked(make_client: Any, kit: Any) -> TestClient:
    client = make_client(api_key=KEY)
    assert client.post("/maps", json=kit.MAP_2D, headers={"Authorization": f"Bearer {KEY}"}).status_code == 201
    return client


@pytest.mark.parametrize(
    ("method", "path"),
    [("GET", "/maps"), ("GET", "/maps/lab"), ("POST", "/maps"), ("DELETE", "/maps/lab"), ("POST", "/maps/lab/scans"),
     ("GET", "/maps/lab/risk"), ("POST", "/maps/lab/risk/query"), ("POST", "/maps/lab/plan"),
     ("GET", "/maps/lab/export/nav2"), ("GET", "/maps/lab/occupancy_grid"), ("GET", "/maps/lab/scans/last")],
)
def test_every_api_call_needs_the_key(locked: TestClient, method: str, path: str) -> None:
    missing = locked.request(method, path)
    assert missing.status_code == 401
    assert missing.headers["WWW-Authenticate"].startswith("Bearer")
    assert "Authorization: Bearer" in error_message(missing)
    wrong = locked.request(method, path, headers={"Authorization": f"Bearer {KEY}x"})
    assert wrong.status_code == 401 and 'error="invalid_token"' in wrong.headers["WWW-Authenticate"]
    basic = locked.request(method, path, headers={"Authorization": f"Basic {KEY}"})
    assert basic.status_code == 401
    assert locked.get("/maps/lab", headers={"Authorization": f"Bearer {KEY}"}).status_code == 200


def test_the_right_key_works_and_probes_stay_open(locked: TestClient, kit: Any) -> None:
    auth = {"Authorization": f"Bearer {KEY}"}
    assert locked.post("/maps/lab/scans", json={"scans": [kit.laser()]}, headers=auth).json()["version"] == 1
    assert locked.get("/health").status_code == 200
    assert locked.get("/metrics").status_code == 200
    assert locked.get("/ui/", follow_redirects=False).status_code == 200  # the page asks for the key itself


def test_the_key_is_checked_before_the_body_is_read(locked: TestClient) -> None:
    # a body far over every limit, with no key or the wrong one: 401, not 413 (nor a parse of it:
    # a 66 MB query body with a wrong key was once parsed before its 401)
    huge = b'{"points": [' + b"[0.0, 0.0]," * 2_000_000 + b"[0.0, 0.0]]}"
    for headers in ({}, {"Authorization": f"Bearer {KEY}x"}):
        response = locked.post("/maps/lab/risk/query", content=huge, headers={"Content-Type": "application/json",
                                                                              **headers})
        assert response.status_code == 401, response.text
    auth = {"Authorization": f"Bearer {KEY}", "Content-Type": "application/json"}
    response = locked.post("/maps/lab/risk/query", content=huge, headers=auth)
    assert response.status_code == 413 and "FUZZYRISK_MAX_JSON_BODY_BYTES" in error_message(response)


def test_routes_other_than_scan_uploads_have_the_small_body_limit(make_client: Any, kit: Any) -> None:
    client = make_client(max_json_body_bytes=2048)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    points = {"points": [[0.0, 0.0]] * 500}  # about 6 KB
    query = client.post("/maps/lab/risk/query", json=points)
    assert query.status_code == 413 and "FUZZYRISK_MAX_JSON_BODY_BYTES" in error_message(query)
    upload = client.post("/maps/lab/scans", json={"scans": [kit.laser(beams=400)]})  # about 8 KB: the big limit
    assert upload.status_code == 200 and upload.json()["version"] == 1


def test_no_key_configured_means_no_check(lab: TestClient) -> None:
    assert lab.get("/maps/lab").status_code == 200


@pytest.mark.parametrize("key", ["short", "x" * 15])
def test_a_short_key_is_refused_at_startup(key: str, tmp_path: Any) -> None:
    with pytest.raises(ValidationError, match="FUZZYRISK_API_KEY"):
        Settings(api_key=key, data_dir=tmp_path)


def test_an_empty_key_variable_means_no_key(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FUZZYRISK_API_KEY", "")
    assert Settings().api_key is None


def test_a_declared_body_over_the_limit_answers_413_before_reading(make_client: Any, kit: Any) -> None:
    client = make_client(max_body_bytes=4096)
    client.post("/maps", json=kit.MAP_2D)
    response = client.post("/maps/lab/scans", json={"scans": [kit.laser(beams=2000)]})
    assert response.status_code == 413
    assert "FUZZYRISK_MAX_BODY_BYTES" in error_message(response)
    assert kit.version(client, "lab") == 0


def test_a_streamed_body_over_the_limit_answers_413_while_reading(make_client: Any, kit: Any) -> None:
    client = make_client(max_body_bytes=4096)
    client.post("/maps", json=kit.MAP_2D)
    sent: list[int] = []

    def chunks() -> Iterator[bytes]:  # no Content-Length: chunked transfer
        for _ in range(100):
            sent.append(1)
            yield b" " * 1024

    for path in ("/maps/lab/scans", "/maps"):
        response = client.post(path, content=chunks(), headers={"Content-Type": "application/json"})
        assert response.status_code == 413, response.text
        assert "FUZZYRISK_MAX_BODY_BYTES" in error_message(response)
    assert kit.version(client, "lab") == 0


def test_validation_errors_do_not_echo_a_huge_input(lab: TestClient, kit: Any) -> None:
    scan = kit.laser(beams=20_000)
    del scan["pose"]["theta"]
    response = lab.post("/maps/lab/scans", json={"scans": [scan]})
    assert response.status_code == 422
    assert len(response.content) < 2000


def test_the_number_of_maps_is_capped_and_the_others_are_unaffected(make_client: Any, kit: Any) -> None:
    client = make_client(max_maps=2)
    for name in ("a", "b"):
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    third = client.post("/maps", json={**kit.MAP_2D, "name": "c"})
    assert third.status_code == 507 and "FUZZYRISK_MAX_MAPS" in error_message(third)
    assert client.post("/maps/a/scans", json={"scans": [kit.laser()]}).json()["version"] == 1
    assert client.delete("/maps/b").status_code == 204
    assert client.post("/maps", json={**kit.MAP_2D, "name": "c"}).status_code == 201


def test_the_cells_of_all_maps_together_are_capped_before_any_memory_is_taken(make_client: Any, kit: Any) -> None:
    client = make_client(max_total_cells=25_000)  # a bayes kit.MAP_2D holds its 100 x 100 = 10,000 cells
    bayes = {**kit.MAP_2D, "model": "bayes"}
    for name in ("a", "b"):
        assert client.post("/maps", json={**bayes, "name": name}).status_code == 201
    third = client.post("/maps", json={**bayes, "name": "c"})
    assert third.status_code == 507
    assert "FUZZYRISK_MAX_TOTAL_CELLS" in error_message(third) and "20,000 of the service's 25,000" in error_message(third)
    assert [m["name"] for m in client.get("/maps").json()] == ["a", "b"]
    small = client.post("/maps", json={**bayes, "name": "c", "size": [5.0, 5.0]})  # 2,500 cells fit
    assert small.status_code == 201


def test_the_cells_fuzzy_maps_hold_count_against_the_total_once_their_scans_take_them(make_client: Any,
                                                                                      kit: Any) -> None:
    client = make_client(max_total_cells=1_500)
    for name in ("a", "b"):  # a fuzzy map holds no cell until a scan reaches one: both are made
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    assert client.post("/maps/a/scans", json={"scans": [kit.laser(x=-4.0, wall=8.0, beams=300)]}).status_code == 200
    held = client.get("/maps/a").json()["held_cells"]
    assert held >= 1_500
    refused = client.post("/maps/b/scans", json={"scans": [kit.laser()]})
    assert refused.status_code == 507 and "FUZZYRISK_MAX_TOTAL_CELLS" in error_message(refused)
    assert client.get("/maps/b").json()["version"] == 0
    assert client.post("/maps/a/clear", json={"min": [-5.0, -5.0], "max": [5.0, 5.0]}).status_code == 200
    assert client.post("/maps/b/scans", json={"scans": [kit.laser()]}).status_code == 200


# ---------------------------------------------------------------- bodies in flight


async def _drain(scope: dict, receive: Any, send: Any) -> None:
    """An ASGI app that reads the whole body, then answers 200."""
    while True:
        message = await receive()
        if not message.get("more_body", False):
            break
    await send({"type": "http.response.start", "status": 200, "headers": []})
    await send({"type": "http.response.body", "body": b"ok"})


def _request(chunks: list[bytes], gate: Any = None) -> tuple[dict, Any, list[dict]]:
    """An HTTP scope, a receive that hands out ``chunks`` (waiting on ``gate`` before the last), and a list
    for what is sent (``_with_send`` makes the ``send``)."""
    scope = {"type": "http", "method": "POST", "path": "/maps/a/scans", "headers": []}
    queue = list(chunks)
    sent: list[dict] = []

    async def receive() -> dict:
        body = queue.pop(0)
        if not queue and gate is not None:
            await gate.wait()
        return {"type": "http.request", "body": body, "more_body": bool(queue)}

    return scope, receive, sent


def _with_send(request: tuple[dict, Any, list[dict]]) -> tuple[dict, Any, Any]:
    scope, receive, sent = request

    async def send(message: dict) -> None:
        sent.append(message)

    return scope, receive, send


def _status(sent: list[dict]) -> int:
    return next(m["status"] for m in sent if m["type"] == "http.response.start")


def test_bodies_in_flight_share_one_budget_and_a_refused_one_gives_its_bytes_back() -> None:
    budget = BodyBudgetMiddleware(ExceptionMiddleware(_drain), max_bytes=10_000, read_timeout_s=5.0)

    async def run() -> tuple[int, int, int, int]:
        gate = asyncio.Event()
        first = _request([b"x" * 6_000, b"x" * 100], gate)  # holds 6,000 bytes while it waits
        second = _request([b"y" * 6_000])  # 6,000 more would pass 10,000
        slow = asyncio.create_task(budget(*_with_send(first)))
        await asyncio.sleep(0.05)
        await budget(*_with_send(second))
        held_while_waiting = budget.in_flight
        gate.set()
        await slow
        third = _request([b"z" * 6_000])  # the first is answered: its bytes are back
        await budget(*_with_send(third))
        return _status(first[2]), _status(second[2]), _status(third[2]), held_while_waiting

    first, second, third, held = asyncio.run(run())
    assert (first, second, third) == (200, 503, 200)
    assert held == 6_000 and budget.in_flight == 0


def test_one_maps_bodies_leave_half_of_the_budget_to_the_others() -> None:
    # bench abuse row 3: forty uploads to one map held the whole budget, and every other map's
    # scans answered 503 with Retry-After 1 s
    budget = BodyBudgetMiddleware(ExceptionMiddleware(_drain), max_bytes=10_000, read_timeout_s=5.0)

    def request(path: str, chunks: list[bytes], gate: Any = None) -> tuple[dict, Any, list[dict]]:
        scope, receive, sent = _request(chunks, gate)
        return {**scope, "path": path}, receive, sent

    async def run() -> list[int]:
        gate = asyncio.Event()
        held = [request("/maps/a/scans", [b"x" * 3_000, b"x"], gate) for _ in range(2)]
        alone = request("/maps/c/scans", [b"z" * 4_000, b"z" * 4_000])  # one body alone: past half, within all
        tasks = [asyncio.create_task(budget(*_with_send(r))) for r in held[:1]]
        await asyncio.sleep(0.05)
        third_of_a = request("/maps/a/scans", [b"x" * 3_000])  # a would hold 6,000: past half of 10,000
        await budget(*_with_send(third_of_a))
        other_map = request("/maps/b/scans", [b"y" * 3_000])  # 6,000 of 10,000 in all: room
        await budget(*_with_send(other_map))
        gate.set()
        await asyncio.gather(*tasks)
        await budget(*_with_send(alone))
        return [_status(third_of_a[2]), _status(other_map[2]), _status(held[0][2]), _status(alone[2])]

    assert asyncio.run(run()) == [503, 200, 200, 200]
    assert budget.in_flight == 0 and budget.by_map == {}


def test_a_stalled_body_answers_408() -> None:
    budget = BodyBudgetMiddleware(ExceptionMiddleware(_drain), max_bytes=10_000, read_timeout_s=0.1)
    never = asyncio.Event()
    request = _request([b"a" * 10, b"b" * 10], never)  # the second chunk never comes
    asyncio.run(budget(*_with_send(request)))
    sent = request[2]
    assert _status(sent) == 408 and budget.in_flight == 0


def test_the_service_runs_the_budget_from_its_settings(make_client: Any, kit: Any) -> None:
    client = make_client(max_bodies_in_flight_bytes=2048)
    client.post("/maps", json=kit.MAP_2D)
    response = client.post("/maps/lab/scans", json={"scans": [kit.laser(beams=400)]})  # about 8 KB
    assert response.status_code == 503 and response.headers["Retry-After"] == "1"
    assert "FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES" in error_message(response)
    assert kit.version(client, "lab") == 0


def test_a_batch_that_would_walk_too_many_cells_is_refused_before_it_is_stored(make_client: Any, kit: Any) -> None:
    # a small request of long rays on a fine map held a fusion thread for minutes, and every
    # restart replayed it; the work is estimated from the rays before the batch is stored
    client = make_client(max_batch_cells=200_000)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201  # 10 m x 10 m at 0.1 m
    far = kit.laser(beams=2_000, ranges=["inf"] * 2_000)  # no-returns to range_max (20 m): clipped at the edge
    refused = client.post("/maps/lab/scans", json={"scans": [far] * 3})
    assert refused.status_code == 413 and "FUZZYRISK_MAX_BATCH_CELLS" in error_message(refused)
    assert kit.version(client, "lab") == 0
    taken = client.post("/maps/lab/scans", json={"scans": [far]})  # 147,150 cells: within the budget
    assert taken.status_code == 200
    assert kit.version(client, "lab") == 1


def test_a_beam_of_an_enormous_range_max_does_not_let_a_batch_past_its_work_budget(make_client: Any,
                                                                                    kit: Any) -> None:
    # range_max 1.5e308 (finite, accepted) overflowed the compiled estimate to a negative count,
    # and a batch over FUZZYRISK_MAX_BATCH_CELLS was fused
    from fuzzyocc import GridSpec, cast_work

    wall = kit.laser(beams=90)
    spec = GridSpec(origin=tuple(kit.MAP_2D["origin"]), size=tuple(kit.MAP_2D["size"]),
                    resolution=kit.MAP_2D["resolution"])
    from app.scans import Limits, from_json
    from app.schemas import ScanBatch

    work = cast_work(spec, from_json(ScanBatch.model_validate({"scans": [wall]}), 2, Limits(256, 10_000)))
    client = make_client(max_batch_cells=work - 1)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    far = {"pose": {"x": 0.05, "y": 0.05, "theta": 0.785398}, "angle_min": 0.0, "angle_increment": 0.0,
           "ranges": ["inf"], "range_min": 0.0, "range_max": 1.5e308}
    refused = client.post("/maps/lab/scans", json={"scans": [wall, far]})
    assert refused.status_code == 413 and "FUZZYRISK_MAX_BATCH_CELLS" in error_message(refused)
    assert kit.version(client, "lab") == 0


def test_the_cast_work_estimate_follows_what_the_cast_walks() -> None:
    import numpy as np

    from fuzzyocc import FuzzyMap, GridSpec, LaserScan, cast_work
    from fuzzyocc.presets import preset

    # sensors inside and outside the map, rays leaving it: the estimate clips them as the cast does
    spec = GridSpec(origin=(-5.0, -5.0), size=(10.0, 10.0), resolution=0.05)
    rng = np.random.default_rng(1)
    for _ in range(8):
        scan = LaserScan(pose=tuple(rng.uniform(-7, 7, 2)) + (float(rng.uniform(-3, 3)),), angle_min=-np.pi,
                         angle_increment=2 * np.pi / 360, ranges=rng.uniform(0.5, 30.0, 360), range_min=0.1,
                         range_max=12.0)
        estimate = cast_work(spec, [scan])
        walked = FuzzyMap(spec, engine=preset("paper")).integrate_batch([scan]).cells_traversed
        assert 0.95 * walked <= estimate <= 1.1 * walked, (estimate, walked)
        # the default engine cuts no-returns beside hits short: it walks less than the estimate
        assert FuzzyMap(spec).integrate_batch([scan]).cells_traversed <= estimate


def test_a_trickled_body_answers_408_once_the_whole_body_is_late() -> None:
    # bench abuse row 4b: a byte every few seconds passed the per-chunk timeout for ever
    budget = BodyBudgetMiddleware(ExceptionMiddleware(_drain), max_bytes=10_000, read_timeout_s=1.0,
                                  body_timeout_s=0.3)
    scope = {"type": "http", "method": "POST", "path": "/maps/a/scans", "headers": []}
    sent: list[dict] = []

    async def trickle() -> dict:
        await asyncio.sleep(0.05)  # well within the per-chunk timeout, every time
        return {"type": "http.request", "body": b"x", "more_body": True}

    async def send(message: dict) -> None:
        sent.append(message)

    started = time.monotonic()
    asyncio.run(budget(scope, trickle, send))
    assert _status(sent) == 408 and 0.3 <= time.monotonic() - started < 1.0
    assert b"FUZZYRISK_BODY_TIMEOUT_S" in b"".join(m.get("body", b"") for m in sent)
    assert budget.in_flight == 0
