"""A robot's session against a real server process: map a hall with a door, plan through the door,
restart (gracefully and with kill -9) and get the same risk back, byte for byte."""

from __future__ import annotations

import json
from typing import Any

import httpx
import numpy as np
import pytest

pytestmark = pytest.mark.slow

ROBOT_RADIUS = 0.25


def _risk_bytes(http: httpx.Client) -> bytes:
    response = http.get("/maps/hall/risk", params={"format": "npy"})
    assert response.status_code == 200
    return response.content


def _dense(path: np.ndarray, step: float = 0.01) -> np.ndarray:
    """The path resampled every ``step`` metres along each segment."""
    pieces = [np.linspace(a, b, max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)) for a, b in zip(path, path[1:])]
    return np.concatenate(pieces)


def _map_the_hall(http: httpx.Client, world: Any) -> None:
    assert http.post("/maps", json=world.MAP).status_code == 201
    poses = world.POSES
    for first in range(0, len(poses), 9):
        batch = {"scans": [world.laser_json(p) for p in poses[first:first + 9]]}
        assert http.post("/maps/hall/scans", json=batch).status_code == 200


def test_a_robot_maps_the_hall_and_plans_through_the_door(start_server: Any, world: Any) -> None:
    server = start_server(FUZZYRISK_PLAN_WARMUP="true")  # as in production: workers start with the server
    with server.client() as http:
        _map_the_hall(http, world)
        request = {"start": [2.0, 1.5], "goal": [8.0, 4.5], "planner": "RRTstar", "time_limit": 1.0,
                   "robot_radius": ROBOT_RADIUS, "max_risk": 0.5, "risk_weight": 1.0, "allow_unknown": False,
                   "seed": 1}
        response = http.post("/maps/hall/plan", json=request)
        assert response.status_code == 200, response.text
        result = response.json()
        assert result["status"] == "exact" and result["max_risk"] <= 0.5

    path = np.asarray(result["path"])
    assert np.allclose(path[0], [2.0, 1.5]) and np.linalg.norm(path[-1] - [8.0, 4.5]) < 0.1
    dense = _dense(path)
    # against the world's TRUE walls: the robot's disc never touches one (less a cell of discretisation)
    clearance = world.distance_to_walls(dense).min()
    assert clearance >= ROBOT_RADIUS - 0.05, clearance
    crossing = dense[np.abs(dense[:, 0] - 5.0) < 0.1]
    assert len(crossing) and (crossing[:, 1] > world.DOOR[0]).all() and (crossing[:, 1] < world.DOOR[1]).all()


def test_restarts_serve_the_same_risk_bytes(start_server: Any, world: Any) -> None:
    server = start_server(FUZZYRISK_SNAPSHOT_EVERY="2")
    with server.client() as http:
        _map_the_hall(http, world)  # 3 batches: a snapshot at 2, one batch after it
        before = _risk_bytes(http)
        info = http.get("/maps/hall").json()
    server.terminate()  # graceful: snapshot at shutdown

    server = start_server(FUZZYRISK_SNAPSHOT_EVERY="2")
    with server.client() as http:
        assert http.get("/maps/hall").json() == info
        assert _risk_bytes(http) == before
        more = {"scans": [world.laser_json((3.0, 2.0, 0.7)), world.laser_json((7.0, 4.0, -0.7))]}
        assert http.post("/maps/hall/scans", json=more).json()["version"] == info["version"] + 1
        after = _risk_bytes(http)
        assert after != before
    server.kill()  # no shutdown at all: the last batch comes back by replay

    server = start_server()
    with server.client() as http:
        assert http.get("/maps/hall").json()["version"] == info["version"] + 1
        assert _risk_bytes(http) == after


def test_the_server_log_stays_one_json_object_a_line_through_a_dubins_rrtstar_plan(start_server: Any,
                                                                                   world: Any) -> None:
    # OMPL warns in plain text about RRTstar on the asymmetric Dubins space (planning/README.md)
    server = start_server(FUZZYRISK_PLAN_WARMUP="true")
    with server.client() as http:
        _map_the_hall(http, world)
        request = {"start": [2.0, 1.5, 0.0], "goal": [8.0, 4.5, 1.57], "planner": "RRTstar", "time_limit": 1.0,
                   "state_space": "Dubins", "turning_radius": 0.5, "robot_radius": ROBOT_RADIUS}
        response = http.post("/maps/hall/plan", json=request)
        assert response.status_code == 200 and response.json()["status"] == "exact", response.text
    server.terminate()  # every worker's output is flushed once the service is gone
    lines = [line for line in server.log().splitlines() if line.strip()]
    assert len(lines) > 5
    for line in lines:
        assert isinstance(json.loads(line), dict), line


def _door_blocked(world: Any) -> dict[str, Any]:
    """A LaserScan from (4.2, 3.0) facing the door: a person standing in it, 0.7 m ahead, 0.76 m wide."""
    angles = np.linspace(-0.5, 0.5, 41)
    return {"pose": {"x": 4.2, "y": 3.0, "theta": 0.0}, "angle_min": -0.5, "angle_increment": 0.025,
            "ranges": (0.7 / np.cos(angles)).round(6).tolist(), "range_min": 0.05, "range_max": world.RANGE_MAX}


def test_a_robot_checks_its_path_until_someone_stands_in_the_door(start_server: Any, world: Any) -> None:
    """Nav2's IsPathValid against a real server: the planned path holds on its version, and is invalid from the
    point before the door once someone stands in it."""
    server = start_server()
    rules = {"robot_radius": ROBOT_RADIUS, "max_risk": 0.5, "allow_unknown": False}
    with server.client() as http:
        _map_the_hall(http, world)
        plan = http.post("/maps/hall/plan", json={"start": [2.0, 1.5], "goal": [8.0, 4.5], "planner": "grid",
                                                  **rules}).json()
        assert plan["status"] == "exact", plan
        path = {"poses": plan["poses"], "header": plan["header"], **rules}  # the nav_msgs/Path as it came
        before = http.post("/maps/hall/paths/check", json=path).json()
        assert before == {"valid": True, "first_invalid_index": None, "max_risk": plan["max_risk"],
                          "cost": plan["cost"], "length": plan["length"], "version": plan["version"]}
        # seen for a moment: five scans outweigh the free space the mapping saw there
        assert http.post("/maps/hall/scans", json={"scans": [_door_blocked(world)] * 5}).status_code == 200
        response = http.post("/maps/hall/paths/check", json=path)
        after = response.json()
        assert not after["valid"] and after["version"] == plan["version"] + 1 == int(response.headers["X-Map-Version"])
        first = after["first_invalid_index"]
        points = np.asarray(plan["path"])
        assert points[first, 0] < 4.9 <= points[first + 1:, 0].max()  # before the door, which the path still crosses
        ahead = http.post("/maps/hall/paths/check", json={**path, "poses": plan["poses"][: first + 1]}).json()
        assert ahead["valid"]  # the robot may drive up to that point
