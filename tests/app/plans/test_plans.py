"""Plans over HTTP: the PlanResult contract, Nav2 error codes, parameter checks, worker processes."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.config import Settings
from app.api.factory import create_app
from planning.planners import UNSUPPORTED


@pytest.fixture(scope="module")
def planner(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """One service for the module (its planner process starts once): map ``lab`` scanned from the origin,
    a wall at x = 3.05 m within +-45 degrees, and the 3-D map ``hall`` with a wall at x = 2.5 m."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("plans"), plan_workers=1, max_plan_time_s=5.0)
    with TestClient(create_app(settings)) as client:
        client.post("/maps", json={"name": "lab", "resolution": 0.1, "origin": [-5.0, -5.0], "size": [10.0, 10.0]})
        angles = -math.pi / 4 + np.arange(181) * (math.pi / 2 / 180)
        scan = {"pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -math.pi / 4,
                "angle_increment": math.pi / 2 / 180, "ranges": (3.05 / np.cos(angles)).tolist(),
                "range_min": 0.1, "range_max": 20.0}
        behind = {**scan, "pose": {"x": -1.0, "y": 0.0, "theta": 0.0}, "ranges": (4.05 / np.cos(angles)).tolist()}
        assert client.post("/maps/lab/scans", json={"scans": [scan, behind]}).status_code == 200
        client.post("/maps", json={"name": "hall", "resolution": 0.2, "origin": [-4.0, -4.0, 0.0],
                                   "size": [8.0, 8.0, 3.0]})
        points = [[2.5, y, z] for y in np.linspace(-2, 2, 21) for z in (-0.6, -0.2, 0.2, 0.6)]
        client.post("/maps/hall/scans", json={"scans": [{"pose": {"position": [0, 0, 1], "orientation": [0, 0, 0, 1]},
                                                          "points": points, "range_max": 10}]})
        yield client


def _plan(client: TestClient, name: str = "lab", **body: Any) -> Any:
    request = {"start": [-1.5, 0.0], "goal": [2.0, 0.5], "planner": "RRTConnect", "time_limit": 1.0,
               "robot_radius": 0.1, "max_risk": 0.6, "seed": 3, **body}
    return client.post(f"/maps/{name}/plan", json=request)


def test_a_plan_answers_the_plan_result_contract(planner: TestClient) -> None:
    response = _plan(planner)
    assert response.status_code == 200, response.text
    result = response.json()
    assert set(result) >= {"status", "path", "length", "max_risk", "mean_risk", "cost", "planner", "planning_time"}
    assert result["status"] == "exact" and result["planner"] == "RRTConnect" and result["state_space"] == "R2"
    assert result["error_code"] is None
    path = np.asarray(result["path"])
    assert path.shape[1] == 2 and np.allclose(path[0], [-1.5, 0.0]) and np.linalg.norm(path[-1] - [2.0, 0.5]) <= 0.11
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    assert result["length"] == pytest.approx(steps.sum(), rel=1e-6)
    assert result["max_risk"] <= 0.6 and result["cost"] >= result["length"] and result["version"] == 1
    risk = planner.post("/maps/lab/risk/query", json={"points": path.tolist()}).json()["risk"]
    assert max(risk) <= result["max_risk"] + 1e-6  # the map's own risk along the path respects the bound


def test_the_grid_planner_and_se2_plans(planner: TestClient) -> None:
    grid = _plan(planner, planner="grid").json()
    assert grid["status"] == "exact" and grid["planner"] == "grid"
    se2 = _plan(planner, start=[-1.5, 0.0, 0.0], goal=[2.0, 0.5, 1.0], state_space="SE2").json()
    assert se2["status"] == "exact" and len(se2["path"][0]) == 3


def test_a_3d_map_plans_in_r3_by_default(planner: TestClient) -> None:
    result = _plan(planner, "hall", start=[-1.0, 0.0, 1.0], goal=[1.5, 1.0, 1.2], planner="grid").json()
    assert result["state_space"] == "R3" and result["status"] == "exact" and len(result["path"][0]) == 3


@pytest.mark.parametrize(
    ("body", "code"),
    [
        ({"start": [-9.0, 0.0]}, "START_OUTSIDE_MAP"),
        ({"goal": [0.0, 7.5]}, "GOAL_OUTSIDE_MAP"),
        ({"start": [3.05, 0.0]}, "START_OCCUPIED"),
        ({"goal": [3.05, 0.5]}, "GOAL_OCCUPIED"),
        ({"start": [0.5, 0.0], "goal": [4.5, 0.0], "allow_unknown": False}, "GOAL_OCCUPIED"),  # never observed
    ],
)
def test_an_unusable_start_or_goal_answers_its_nav2_code(planner: TestClient, body: dict, code: str) -> None:
    response = _plan(planner, **body)
    assert response.status_code == 422
    body = response.json()
    assert body["code"] == code and body["message"]


def test_a_plan_out_of_time_answers_200_with_nav2s_timeout(planner: TestClient) -> None:
    # behind the wall: the way round its end is far longer than a millisecond of sampling finds (a
    # car-like robot: in R2 the grid planner's seed would find it)
    response = _plan(planner, planner="RRTstar", state_space="Dubins", start=[-1.5, 0.0, 0.0], goal=[4.5, 0.0, 0.0],
                     turning_radius=0.5, time_limit=0.001, seed=None)
    assert response.status_code == 200, response.text
    result = response.json()
    assert result["status"] in ("approximate", "none") and result["error_code"] == "TIMEOUT", result
    assert result["message"]  # says how far from the goal, or that no path was found


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ({"planner": "Teleport"}, "RRTConnect"),  # lists the planners that work
        ({"planner": next(iter(UNSUPPORTED))}, next(iter(UNSUPPORTED.values()))),  # says why it is left out
        ({"state_space": "R3"}, "R2"),
        ({"state_space": "Warp"}, "ReedsShepp"),
        ({"start": [0.0, 0.0, 0.0]}, "start"),
        ({"time_limit": 60}, "FUZZYRISK_MAX_PLAN_TIME_S"),
        ({"time_limit": 0}, "time_limit"),
        ({"max_risk": 1.5}, "max_risk"),
        ({"robot_radius": -1}, "robot_radius"),
        ({"seed": -1}, "seed"),
        ({"state_space": "Dubins", "start": [0, 0, 0], "goal": [1, 0, 0]}, "turning_radius"),
        # bounded by what the map makes sensible, before any work (1e6 was a MemoryError)
        ({"robot_radius": 1e6}, "robot_radius"),
        ({"state_space": "ReedsShepp", "start": [-1.5, 0, 0], "goal": [2.0, 0.5, 0], "turning_radius": 1e300},
         "turning_radius"),
        ({"goal_tolerance": 1e300}, "goal_tolerance"),
        ({"risk_weight": 1e300}, "risk_weight"),
    ],
)
def test_bad_plan_parameters_answer_422_saying_what_to_fix(planner: TestClient, body: dict, needle: str) -> None:
    response = _plan(planner, **body)
    assert response.status_code == 422, response.text
    assert needle in str(response.json())


@pytest.mark.parametrize("token", ["NaN", "Infinity"])
def test_non_finite_plan_parameters_are_refused(planner: TestClient, token: str) -> None:
    body = '{"start": [0, %s], "goal": [1, 0]}' % token
    response = planner.post("/maps/lab/plan", content=body, headers={"Content-Type": "application/json"})
    assert response.status_code == 422 and "start" in str(response.json())


def test_plans_are_counted_by_planner_and_outcome(planner: TestClient) -> None:
    _plan(planner)
    _plan(planner, start=[-9.0, 0.0])
    text = planner.get("/metrics").text
    assert 'fuzzyrisk_plan_duration_seconds_count{outcome="exact",planner="RRTConnect"}' in text
    assert 'fuzzyrisk_plan_duration_seconds_count{outcome="rejected",planner="RRTConnect"}' in text


def test_the_documented_plan_example_works_when_pasted(planner: TestClient) -> None:
    spec = planner.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    example_map = schemas["MapCreate"]["examples"][0]
    planner.delete(f"/maps/{example_map['name']}")
    assert planner.post("/maps", json=example_map).status_code == 201
    scans = spec["paths"]["/maps/{name}/scans"]["post"]["requestBody"]["content"]["application/json"]["examples"]
    assert planner.post(f"/maps/{example_map['name']}/scans", json=scans["laser"]["value"]).status_code == 200
    (example_plan,) = schemas["PlanRequest"]["examples"]
    response = planner.post(f"/maps/{example_map['name']}/plan", json=example_plan)
    assert response.status_code == 200, response.text
    assert response.json()["status"] == "exact"


def test_planners_lists_what_a_plan_request_accepts(planner: TestClient) -> None:
    listing = planner.get("/planners").json()
    names = [p["name"] for p in listing["planners"]]
    assert names[0] == "grid" and "RRTConnect" in names and "RRTstar" in names
    assert "R2" in listing["state_spaces"] and "R3" in listing["state_spaces"]
    for entry in listing["planners"]:
        if entry["name"] == "RRTConnect":
            assert entry["optimizing"] is False
    # every listed name is one the plan route takes (no 422 for the name itself)
    for name in names:
        response = _plan(planner, planner=name, time_limit=0.2, seed=None)
        assert response.status_code == 200, (name, response.text)
