"""Concurrency against a real server: batches to one map all land, one at a time in arrival order;
/health answers in milliseconds while plans (worker processes) and fusion (threads) run; a path check does not
wait for the planner workers."""

from __future__ import annotations

import io
import statistics
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest

from fuzzyocc import FuzzyMap, GridSpec, LaserScan, SensorModel

pytestmark = pytest.mark.slow


def test_concurrent_batches_to_one_map_all_land_one_at_a_time(start_server: Any, world: Any) -> None:
    server = start_server()
    poses = [(x + 0.1 * k, y, th) for k, (x, y, th) in enumerate(world.POSES)][:24]
    bodies = [{"scans": [world.laser_json(p, beams=360)]} for p in poses]
    with server.client() as http:
        assert http.post("/maps", json=world.MAP).status_code == 201

    def post(body: dict[str, Any]) -> int:
        with server.client() as http:
            response = http.post("/maps/hall/scans", json=body)
            assert response.status_code == 200, response.text
            return int(response.json()["version"])

    with ThreadPoolExecutor(6) as pool:
        versions = list(pool.map(post, bodies))
    assert sorted(versions) == list(range(1, len(bodies) + 1))
    with server.client() as http:
        info = http.get("/maps/hall").json()
        held = np.load(io.BytesIO(http.get("/maps/hall/risk", params={"format": "npy"}).content))
    assert info["version"] == len(bodies) and info["scans_fused"] == len(bodies)

    # applied whole and in version order: a fusion of the batches in that order gives the same bytes
    spec = world.MAP
    fresh = FuzzyMap(GridSpec(origin=spec["origin"], size=spec["size"], resolution=spec["resolution"]),
                     SensorModel(**spec["sensor"]))
    for _, body in sorted(zip(versions, bodies), key=lambda vb: vb[0]):
        (s,) = body["scans"]
        ranges = np.array([np.inf if r == "inf" else r for r in s["ranges"]], dtype=np.float64)
        fresh.integrate_batch([LaserScan(pose=(s["pose"]["x"], s["pose"]["y"], s["pose"]["theta"]),
                                         angle_min=s["angle_min"], angle_increment=s["angle_increment"],
                                         ranges=ranges, range_min=s["range_min"], range_max=s["range_max"])])
    assert held.tobytes() == np.ascontiguousarray(fresh.risk()).tobytes()


def test_health_answers_in_milliseconds_while_plans_and_fusion_run(start_server: Any, world: Any) -> None:
    server = start_server(FUZZYRISK_PLAN_WARMUP="true")
    with server.client() as http:
        assert http.post("/maps", json=world.MAP).status_code == 201
        assert http.post("/maps", json={**world.MAP, "name": "busy"}).status_code == 201
        assert http.post("/maps/hall/scans", json={"scans": [world.laser_json(p) for p in world.POSES]}).status_code == 200
        # a first plan, so that the worker is up and the measured window is solving, not starting
        warm = {"start": [2.0, 1.5], "goal": [8.0, 4.5], "planner": "RRTConnect", "time_limit": 1.0}
        assert http.post("/maps/hall/plan", json=warm).status_code == 200

    stop = threading.Event()
    busy: dict[str, int] = {"plans": 0, "batches": 0}

    def plans() -> None:
        long_plan = {"start": [2.0, 1.5], "goal": [8.0, 4.5], "planner": "RRTstar", "time_limit": 2.0}
        with server.client() as http:
            while not stop.is_set():
                assert http.post("/maps/hall/plan", json=long_plan).status_code == 200
                busy["plans"] += 1

    def fusion() -> None:
        batch = {"scans": [world.laser_json(p, beams=1440) for p in world.POSES]}
        with server.client() as http:
            while not stop.is_set():
                assert http.post("/maps/busy/scans", json=batch).status_code == 200
                busy["batches"] += 1

    workers = [threading.Thread(target=plans), threading.Thread(target=fusion)]
    for worker in workers:
        worker.start()
    time.sleep(0.3)
    latencies = []
    with server.client() as http:
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            started = time.perf_counter()
            assert http.get("/health").status_code == 200
            latencies.append(time.perf_counter() - started)
            time.sleep(0.02)
    stop.set()
    for worker in workers:
        worker.join(timeout=30)
    assert busy["batches"] >= 1 and busy["plans"] >= 1  # the window really was busy
    # a plan holds the GIL for its whole solve (2 s here): on the event loop it would show here. The
    # bound on the slowest answer is half that solve: on 2 cores shared with two planner processes
    # and a fusion thread, one answer once took 0.52 s (a clean-clone CI run, 2026-12-02) while the
    # others took 2-24 ms, and such a gap is the scheduler's, not a stalled loop's
    assert statistics.median(latencies) < 0.05, latencies
    assert max(latencies) < 1.0, latencies


def _plans_handed_to_workers(http: Any) -> float:
    """How many plans the server has handed a grid to a worker for (counted just before they go to one)."""
    text = http.get("/metrics").text
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
               if line.startswith("fuzzyrisk_plan_grids_total{"))


def test_a_path_check_answers_while_a_long_plan_holds_the_only_planner_worker(start_server: Any, world: Any) -> None:
    server = start_server(FUZZYRISK_PLAN_WARMUP="true")  # one planner worker (the fixture's), up before /ready
    rules = {"robot_radius": 0.25, "max_risk": 0.5}
    with server.client() as http:
        assert http.post("/maps", json=world.MAP).status_code == 201
        assert http.post("/maps/hall/scans", json={"scans": [world.laser_json(p) for p in world.POSES]}).status_code == 200
        quick = http.post("/maps/hall/plan", json={"start": [2.0, 1.5], "goal": [8.0, 4.5], "planner": "grid",
                                                   **rules}).json()
        assert quick["status"] == "exact" and _plans_handed_to_workers(http) == 1

    def long_plan() -> int:  # an anytime optimizer, unseeded: it holds the worker for its whole time limit
        with server.client() as http:
            return http.post("/maps/hall/plan", json={"start": [2.0, 1.5], "goal": [8.0, 4.5], "planner": "RRTstar",
                                                      "time_limit": 5.0, **rules}).status_code

    with ThreadPoolExecutor(1) as pool, server.client() as http:
        running = pool.submit(long_plan)
        deadline = time.monotonic() + 30
        while _plans_handed_to_workers(http) < 2:  # the long plan is on its way into the worker
            assert time.monotonic() < deadline and not running.done()
            time.sleep(0.01)
        check = http.post("/maps/hall/paths/check", json={"path": quick["path"], **rules})
        assert check.status_code == 200 and check.json()["valid"], check.text
        assert not running.done()  # answered while the plan still held the worker
        assert running.result() == 200
