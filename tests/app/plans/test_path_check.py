"""Path checks over HTTP (POST /maps/{name}/paths/check, Nav2's IsPathValid): a plan's own path passes on its
version, obstacles, unknown space and the map's edge make a path invalid at the right point, bad input is named."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.factory import create_app
from app.config import Settings
from planning.path_check import MAX_WALK_CELLS

RULES = {"robot_radius": 0.1, "max_risk": 0.45, "risk_weight": 2.0, "allow_unknown": True}


def _wall_scan(x: float, wall: float) -> dict[str, Any]:
    """A LaserScan from (x, 0) facing +x, +-45 degrees, onto a wall ``wall`` metres ahead."""
    angles = -math.pi / 4 + np.arange(181) * (math.pi / 2 / 180)
    return {"pose": {"x": x, "y": 0.0, "theta": 0.0}, "angle_min": -math.pi / 4,
            "angle_increment": math.pi / 2 / 180, "ranges": (wall / np.cos(angles)).tolist(),
            "range_min": 0.1, "range_max": 20.0}


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """One service for the module: map ``lab`` (10 m square at 0.1 m) scanned from the origin and from (-1, 0) onto a
    wall at x = 3.05 m (cells outside the scans' +-45 degrees never observed), and the 3-D map ``hall`` with a wall
    at x = 2.5 m."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("paths"), plan_workers=1, max_plan_time_s=5.0)
    with TestClient(create_app(settings)) as client:
        client.post("/maps", json={"name": "lab", "resolution": 0.1, "origin": [-5.0, -5.0], "size": [10.0, 10.0]})
        scans = [_wall_scan(0.0, 3.05), _wall_scan(-1.0, 4.05)]
        assert client.post("/maps/lab/scans", json={"scans": scans}).status_code == 200
        client.post("/maps", json={"name": "hall", "resolution": 0.2, "origin": [-4.0, -4.0, 0.0],
                                   "size": [8.0, 8.0, 3.0]})
        points = [[2.5, y, z] for y in np.linspace(-2, 2, 21) for z in (-0.6, -0.2, 0.2, 0.6)]
        cloud = {"pose": {"position": [0, 0, 1], "orientation": [0, 0, 0, 1]}, "points": points, "range_max": 10}
        assert client.post("/maps/hall/scans", json={"scans": [cloud]}).status_code == 200
        yield client


def _check(client: TestClient, name: str = "lab", **body: Any) -> Any:
    response = client.post(f"/maps/{name}/paths/check", json={**RULES, **body})
    assert response.status_code == 200, response.text
    assert response.headers["X-Map-Version"] == str(response.json()["version"])
    return response.json()


@pytest.mark.parametrize(("map_name", "request_body"), [
    ("lab", {"planner": "grid", "start": [-0.5, 0.0], "goal": [2.0, 1.0]}),
    ("lab", {"planner": "RRTConnect", "start": [-0.5, 0.0], "goal": [2.0, 1.0], "seed": 2}),
    ("lab", {"planner": "RRTConnect", "state_space": "SE2", "start": [-0.5, 0.0, 0.0], "goal": [2.0, 1.0, 1.5],
             "seed": 2}),
    ("lab", {"planner": "RRTConnect", "state_space": "Dubins", "start": [-0.5, 0.0, 0.0], "goal": [2.0, 1.0, 1.5],
             "turning_radius": 0.5, "seed": 2}),
    # a 3-D map's cloud observed little but its beams: unknown space allowed
    ("hall", {"planner": "grid", "start": [-1.0, 0.0, 1.0], "goal": [1.5, 1.0, 1.2], "allow_unknown": True}),
])
def test_a_path_the_planner_just_returned_is_valid_on_the_same_version(
        service: TestClient, map_name: str, request_body: dict[str, Any]) -> None:
    request_body = {**RULES, "allow_unknown": False, **request_body}
    plan = service.post(f"/maps/{map_name}/plan", json=request_body).json()
    assert plan["status"] == "exact", plan
    rules = {key: request_body[key] for key in (*RULES, "state_space") if key in request_body}
    for given in ({"path": plan["path"]}, {"poses": plan["poses"], "header": plan["header"]}):
        checked = _check(service, map_name, **given, **rules)
        assert checked["valid"] and checked["first_invalid_index"] is None and checked["version"] == plan["version"]
        if request_body.get("state_space") == "Dubins":  # the plan measured its curve finer than a point a cell
            assert checked["cost"] == pytest.approx(plan["cost"], rel=1e-3)
        else:  # the planner's own measures of the path it returned
            assert (checked["cost"], checked["length"], checked["max_risk"]) == (
                plan["cost"], plan["length"], plan["max_risk"])


def test_a_segment_through_the_wall_is_invalid_from_its_first_point(service: TestClient) -> None:
    path = [[-0.5, 0.0], [1.0, 0.0], [2.5, 0.0], [4.0, 0.0], [4.5, 0.0]]  # the wall is at x = 3.05 m
    checked = _check(service, path=path)
    assert not checked["valid"] and checked["first_invalid_index"] == 2 and checked["max_risk"] > 0.45
    assert checked["length"] == pytest.approx(5.0) and checked["cost"] > checked["length"]
    assert _check(service, path=path[:3])["valid"]  # what comes before it is drivable


def test_never_observed_space_is_invalid_without_allow_unknown(service: TestClient) -> None:
    path = [[0.5, 0.0], [0.5, -2.0]]  # out of the scans' +-45 degrees: never observed
    assert _check(service, path=path, allow_unknown=True)["valid"]
    refused = _check(service, path=path, allow_unknown=False)
    assert not refused["valid"] and refused["first_invalid_index"] == 0


def test_a_point_off_the_map_is_invalid_and_leaves_the_path_unmeasured(service: TestClient) -> None:
    checked = _check(service, path=[[0.5, 0.0], [1.0, 0.0], [1.0, -6.0]])  # the map ends at y = -5 m
    assert not checked["valid"] and checked["first_invalid_index"] == 1
    assert checked["length"] is checked["cost"] is checked["max_risk"] is None
    one = _check(service, path=[[5.0, 0.0]])  # the map's upper edge is not on it
    assert not one["valid"] and one["first_invalid_index"] == 0


def test_a_path_made_invalid_by_new_scans_is_invalid_at_the_new_version(service: TestClient) -> None:
    """What Nav2's IsPathValid is for: the map changed under the path the robot drives."""
    assert service.post("/maps", json={"name": "yard", "resolution": 0.1, "origin": [-2.0, -3.0],
                                       "size": [6.0, 6.0]}).status_code == 201
    assert service.post("/maps/yard/scans", json={"scans": [_wall_scan(0.0, 3.05)]}).status_code == 200
    plan = service.post("/maps/yard/plan", json={**RULES, "planner": "grid", "start": [0.3, 0.0],
                                                 "goal": [2.5, 0.0]}).json()
    before = _check(service, "yard", path=plan["path"])
    assert before["valid"] and before["version"] == plan["version"] == 1
    # someone stands across the way at x = 1.5 m, seen twice
    assert service.post("/maps/yard/scans", json={"scans": [_wall_scan(0.0, 1.5)] * 2}).status_code == 200
    after = _check(service, "yard", path=plan["path"])
    assert not after["valid"] and after["version"] == 2
    first = after["first_invalid_index"]
    path = np.asarray(plan["path"])
    assert path[first, 0] < 1.5 <= path[first + 1, 0] + RULES["robot_radius"] + 0.1  # the segment that reaches them
    assert _check(service, "yard", path=plan["path"][: first + 1])["valid"]


@pytest.mark.parametrize(("body", "needle"), [
    ({"path": [[0.5, 0.0], [1.0, 0.0, 0.0]]}, "path[1]: R2 needs (x, y)"),
    ({"path": [[0.5, 0.0]], "state_space": "SE2"}, "path[0]: SE2 needs (x, y, theta)"),
    ({"path": [[0.5, 0.0]], "state_space": "R3"}, "state_space: R3 needs a 3-D field"),
    ({"path": [[0.5, 0.0]], "state_space": "Warp"}, "ReedsShepp"),
    ({"path": []}, "path"),
    ({}, "neither was given"),
    ({"path": [[0.5, 0.0]], "poses": []}, "poses"),
    ({"path": [[0.5, 0.0]], "robot_radius": 1e6}, "robot_radius"),
    ({"path": [[0.5, 0.0]], "robot_radius": -1}, "robot_radius"),
    ({"path": [[0.5, 0.0]], "max_risk": 1.5}, "max_risk"),
    ({"path": [[0.5, 0.0]], "risk_weight": 1e300}, "risk_weight"),
    ({"path": [[0.5, 0.0]], "planner": "grid"}, "planner"),  # a check plans nothing
    ({"path": [[0.5, 0.0]], "header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": "map"}}, "header"),
])
def test_bad_checks_answer_422_naming_what_to_fix(service: TestClient, body: dict[str, Any], needle: str) -> None:
    response = service.post("/maps/lab/paths/check", json=body)
    assert response.status_code == 422, response.text
    assert needle in str(response.json())


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_points_and_poses_are_refused(service: TestClient, token: str) -> None:
    headers = {"Content-Type": "application/json"}

    def send(body: dict[str, Any]) -> Any:  # the token where "T" is: JSON itself has no such number
        return service.post("/maps/lab/paths/check", content=json.dumps(body).replace('"T"', token), headers=headers)

    response = send({"path": [[0, 0], [1, "T"]]})
    assert response.status_code == 422 and "path" in str(response.json())
    pose = {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": "map"},
            "pose": {"position": {"x": 0, "y": 0, "z": 0}, "orientation": {"x": 0, "y": 0, "z": "T", "w": 1}}}
    response = send({"poses": [pose]})
    assert response.status_code == 422 and "orientation" in str(response.json())


def test_poses_in_another_frame_are_refused_naming_the_header(service: TestClient) -> None:
    plan = service.post("/maps/lab/plan", json={**RULES, "planner": "grid", "start": [-0.5, 0.0],
                                                "goal": [2.0, 1.0]}).json()
    poses = [dict(p) for p in plan["poses"]]
    poses[3] = {**poses[3], "header": {**poses[3]["header"], "frame_id": "odom"}}
    response = service.post("/maps/lab/paths/check", json={"poses": poses})
    assert response.status_code == 422 and "poses[3].header.frame_id 'odom'" in response.json()["message"]
    response = service.post("/maps/lab/paths/check", json={"poses": plan["poses"],
                                                            "header": {**plan["header"], "frame_id": "odom"}})
    assert response.status_code == 422 and "header.frame_id" in response.json()["message"]
    # an empty frame_id is the path's own, as ROS reads it
    blank = [{**p, "header": {**p["header"], "frame_id": ""}} for p in plan["poses"]]
    assert _check(service, poses=blank)["valid"]


def test_a_check_is_bounded_before_any_work(service: TestClient) -> None:
    response = service.post("/maps/lab/paths/check", json={"path": [[0.5, 0.0]] * 10_001})
    assert response.status_code == 413 and "FUZZYRISK_MAX_PATH_POINTS" in response.json()["message"]
    # a corridor 2,000 cells long, crossed end to end by every segment of a path of 10,000 points
    assert service.post("/maps", json={"name": "corridor", "resolution": 0.05, "origin": [0.0, 0.0],
                                       "size": [100.0, 0.5]}).status_code == 201
    zigzag = [[0.01 + 99.98 * (k % 2), 0.25] for k in range(10_000)]
    assert 9_999 * 2_000 > MAX_WALK_CELLS
    response = service.post("/maps/corridor/paths/check", json={"path": zigzag})
    assert response.status_code == 413 and "check it in parts" in response.json()["message"], response.text
    assert _check(service, "corridor", path=zigzag[:100])["length"] == pytest.approx(99 * 99.98)


def test_the_documented_check_example_works_when_pasted(service: TestClient) -> None:
    spec = service.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    example_map = schemas["MapCreate"]["examples"][0]
    service.delete(f"/maps/{example_map['name']}")
    assert service.post("/maps", json=example_map).status_code == 201
    scans = spec["paths"]["/maps/{name}/scans"]["post"]["requestBody"]["content"]["application/json"]["examples"]
    assert service.post(f"/maps/{example_map['name']}/scans", json=scans["laser"]["value"]).status_code == 200
    (example,) = schemas["PathCheckRequest"]["examples"]
    response = service.post(f"/maps/{example_map['name']}/paths/check", json=example)
    assert response.status_code == 200, response.text
    assert response.json()["valid"] is True
