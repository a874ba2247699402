"""Growing maps over HTTP: no box, bounds that follow the scans, clears and forgetting replayed, limits refused."""

from __future__ import annotations

import io
import re
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from scipy.spatial.transform import Rotation

from app.config import Settings
from tests.conftest import error_message, ouster_frames

GROWING = {"name": "explore", "resolution": 0.1}


def _query(client: TestClient, points: list[list[float]], name: str = "explore") -> list[float]:
    response = client.post(f"/maps/{name}/risk/query", json={"points": points})
    assert response.status_code == 200, response.text
    return response.json()["risk"]


def _info(client: TestClient, name: str = "explore") -> dict[str, Any]:
    response = client.get(f"/maps/{name}")
    assert response.status_code == 200, response.text
    return response.json()


def test_a_map_without_a_box_grows_where_the_scans_reach(client: TestClient, kit: Any) -> None:
    made = client.post("/maps", json=GROWING)
    assert made.status_code == 201, made.text
    info = made.json()
    assert info["extent"] == "growing" and info["dimensions"] == 2
    assert info["origin"] is info["size"] is info["shape"] is info["bounds"] is None
    assert info["held_cells"] == 0
    assert client.post("/maps/explore/scans", json={"scans": [kit.laser(x=5000.0, y=-7000.0)]}).status_code == 200
    info = _info(client)
    lo, hi = info["bounds"]["min"], info["bounds"]["max"]
    assert lo[0] <= 5000.0 < hi[0] and lo[1] <= -7000.0 < hi[1]
    assert info["origin"] == lo and info["shape"] == [round((h - m) / 0.1) for m, h in zip(lo, hi)]
    assert 0 < info["held_cells"] < 10_000  # a scan's worth, not the 5 km in between
    # anywhere is answered: the wall is seen, the space nobody saw is unknown
    wall, free, never = _query(client, [[5003.05, -7000.0], [5001.0, -7000.0], [-300.0, 12.0]])
    assert wall > 0.5 > free and never == 0.5


def test_a_growing_map_comes_back_the_same_after_a_restart(make_client: Any, kit: Any) -> None:
    client = make_client(snapshot_every=3)
    assert client.post("/maps", json={**GROWING, "forget_beyond": 30.0}).status_code == 201
    for i in range(5):  # a snapshot after the third, two batches replayed after it
        assert client.post("/maps/explore/scans", json={"scans": [kit.laser(x=-2.0 * i, y=1.5 * i)]}).status_code == 200
    points = np.random.default_rng(0).uniform(-12.0, 6.0, (400, 2)).tolist()
    before, info = _query(client, points), _info(client)
    again = make_client(snapshot_every=3)
    assert _query(again, points) == before
    after = _info(again)
    assert after["bounds"] == info["bounds"] and after["held_cells"] == info["held_cells"]
    assert after["forget_beyond"] == 30.0 and after["extent"] == "growing"


def test_clearing_a_region_is_durable_and_replayed(make_client: Any, kit: Any) -> None:
    client = make_client()
    assert client.post("/maps", json=GROWING).status_code == 201
    assert client.post("/maps/explore/scans", json={"scans": [kit.laser(wall=3.0)]}).status_code == 200
    assert _query(client, [[3.05, 0.0]])[0] > 0.5
    cleared = client.post("/maps/explore/clear", json={"min": [2.5, -1.0], "max": [3.5, 1.0]})
    assert cleared.status_code == 200, cleared.text
    assert cleared.json()["cells_cleared"] > 0 and cleared.json()["version"] == 2
    assert _query(client, [[3.05, 0.0]]) == [0.5]
    restarted = make_client()
    assert _query(restarted, [[3.05, 0.0], [1.0, 0.0]]) == _query(client, [[3.05, 0.0], [1.0, 0.0]])
    again = restarted.post("/maps/explore/clear", json={"min": [2.5, -1.0], "max": [3.5, 1.0]})
    assert again.json()["cells_cleared"] == 0


@pytest.mark.parametrize(("body", "named"), [
    ({"min": [0.0, 0.0, 0.0], "max": [1.0, 1.0, 1.0]}, "coordinates"),
    ({"min": [1.0, 0.0], "max": [0.0, 1.0]}, "max[0]"),
    ({"min": [0.0, 0.0], "max": [2e7, 1.0]}, "max"),
])
def test_a_bad_clear_is_refused_and_changes_nothing(lab: TestClient, kit: Any, body: dict[str, Any], named: str) -> None:
    assert lab.post("/maps/lab/scans", json={"scans": [kit.laser(wall=3.0)]}).status_code == 200
    response = lab.post("/maps/lab/clear", json=body)
    assert response.status_code == 422 and named in error_message(response)
    assert _info(lab, "lab")["version"] == 1
    nan = lab.post("/maps/lab/clear", content=b'{"min": [NaN, 0], "max": [1, 1]}',
                   headers={"Content-Type": "application/json"})
    assert nan.status_code == 422


def test_forgetting_far_space_is_a_setting_changed_in_the_maps_line(make_client: Any, kit: Any) -> None:
    client = make_client()
    assert client.post("/maps", json=GROWING).status_code == 201
    assert client.post("/maps/explore/scans", json={"scans": [kit.laser(wall=3.0)]}).status_code == 200
    changed = client.patch("/maps/explore", json={"forget_beyond": 10.0})
    assert changed.status_code == 200 and changed.json()["forget_beyond"] == 10.0
    assert changed.json()["version"] == 2
    # the robot drives 40 m away: the wall it saw first is forgotten, the wall it sees now is kept
    assert client.post("/maps/explore/scans", json={"scans": [kit.laser(x=40.0, wall=3.0)]}).status_code == 200
    first, now = _query(client, [[3.05, 0.0], [43.05, 0.0]])
    assert first == 0.5 and now > 0.5
    assert _info(client)["bounds"]["min"][0] > 30.0
    restarted = make_client()
    assert _info(restarted)["forget_beyond"] == 10.0
    assert _query(restarted, [[3.05, 0.0], [43.05, 0.0]]) == [first, now]
    assert restarted.patch("/maps/explore", json={"forget_beyond": None}).json()["forget_beyond"] is None
    assert restarted.patch("/maps/explore", json={"forget_beyond": -1}).status_code == 422


@pytest.mark.parametrize(("body", "named"), [
    ({**GROWING, "origin": [0.0, 0.0]}, "size"),
    ({**GROWING, "extent": "growing", "origin": [0.0, 0.0], "size": [1.0, 1.0]}, "origin and size"),
    ({**GROWING, "model": "bayes"}, "box"),
    ({**GROWING, "resolution": 0.001}, "at least"),
    ({**GROWING, "forget_beyond": 0.0}, "forget_beyond"),
])
def test_a_growing_map_that_cannot_be_is_refused(client: TestClient, body: dict[str, Any], named: str) -> None:
    response = client.post("/maps", json=body)
    assert response.status_code == 422 and named in str(response.json()), response.text
    assert client.get("/maps").json() == []


@pytest.mark.parametrize("scan", [
    {"x": 2e6},  # the sensor
    {"ranges": [1.5e6] * 90, "range_max": 2e6},  # the hits
])
def test_a_pose_or_point_too_far_from_the_frame_is_refused(client: TestClient, kit: Any, scan: dict[str, Any]) -> None:
    assert client.post("/maps", json=GROWING).status_code == 201
    response = client.post("/maps/explore/scans", json={"scans": [kit.laser(**scan)]})
    assert response.status_code == 422 and "local map frame" in error_message(response)
    assert _info(client)["version"] == 0


def test_a_cloud_is_refused_for_a_hit_too_far_from_the_frame_not_for_a_far_no_return(client: TestClient) -> None:
    assert client.post("/maps", json=GROWING).status_code == 201
    near = [[2.0, 0.5], [2.5, -0.5]]

    def post(far: list[float], range_max: float) -> Any:
        cloud = {"pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "points": [*near, far], "range_max": range_max}
        return client.post("/maps/explore/scans", json={"scans": [cloud]})

    response = post([1.5e6, 0.0], 2e6)  # a hit there
    assert response.status_code == 422 and "local map frame" in error_message(response)
    assert _info(client)["version"] == 0
    response = post([1.5e6, 0.0], 5.0)  # beyond range_max: free space up to 5 m, no hit out there
    assert response.status_code == 200, response.text
    assert response.json()["rays"] == 3


def test_a_batch_that_would_take_too_many_new_cells_is_refused_before_any_work(make_client: Any, kit: Any) -> None:
    client = make_client(max_new_cells_per_batch=2_000)
    assert client.post("/maps", json=GROWING).status_code == 201
    response = client.post("/maps/explore/scans", json={"scans": [kit.laser(wall=15.0, beams=400)]})
    assert response.status_code == 413 and "FUZZYRISK_MAX_NEW_CELLS_PER_BATCH" in error_message(response)
    info = _info(client)
    assert info["version"] == 0 and info["held_cells"] == 0
    assert client.post("/maps/explore/scans", json={"scans": [kit.laser(wall=1.0, beams=20)]}).status_code == 200


def test_every_grid_read_of_a_growing_map_covers_its_bounds(client: TestClient, kit: Any) -> None:
    assert client.post("/maps", json=GROWING).status_code == 201
    empty = client.get("/maps/explore/risk", params={"format": "npy"})
    assert empty.status_code == 409 and "observed nothing yet" in error_message(empty)
    assert client.post("/maps/explore/scans", json={"scans": [kit.laser(x=-20.0, y=7.0)]}).status_code == 200
    info = _info(client)
    risk = np.load(io.BytesIO(client.get("/maps/explore/risk", params={"format": "npy"}).content))
    assert list(risk.shape) == info["shape"]
    as_json = client.get("/maps/explore/risk").json()
    assert as_json["origin"] == info["origin"] and as_json["shape"] == info["shape"]
    grid = client.get("/maps/explore/occupancy_grid").json()
    assert [grid["info"]["width"], grid["info"]["height"]] == info["shape"]
    assert grid["info"]["origin"]["position"]["x"] == info["origin"][0]
    png = client.get("/maps/explore/risk", params={"format": "png"})
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.headers["X-Map-Shape"] == ",".join(str(n) for n in info["shape"])
    assert [float(v) for v in png.headers["X-Map-Origin"].split(",")] == info["origin"]
    # a window of a growing map is cut to its bounds, and says where it is
    part = client.get("/maps/explore/risk", params={"format": "npy", "min": "-25,6", "max": "-19,8"})
    assert part.status_code == 200
    assert float(part.headers["X-Map-Origin"].split(",")[0]) == info["origin"][0] == -20.0  # cut at the bounds
    assert client.get("/maps/explore/export/nav2").status_code == 200


def test_a_plan_on_a_growing_map_may_start_and_end_outside_its_bounds(client: TestClient, kit: Any) -> None:
    assert client.post("/maps", json=GROWING).status_code == 201
    assert client.post("/maps/explore/scans", json={"scans": [kit.laser(wall=3.0)]}).status_code == 200
    lo, hi = _info(client)["bounds"]["min"], _info(client)["bounds"]["max"]
    start, goal = [lo[0] - 5.0, 0.0], [hi[0] + 5.0, 0.5]  # both in space no scan reached
    refused = client.post("/maps/explore/plan", json={"start": start, "goal": goal, "planner": "grid",
                                                       "allow_unknown": False})
    assert refused.status_code == 422 and "unknown" in str(refused.json()).lower(), refused.text
    plan = client.post("/maps/explore/plan", json={"start": start, "goal": goal, "planner": "grid",
                                                    "allow_unknown": True})
    assert plan.status_code == 200, plan.text
    path = np.array([[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in plan.json()["poses"]])
    assert np.allclose(path[0], start, atol=0.1) and np.allclose(path[-1], goal, atol=0.1)
    # it goes around the wall the scan saw (x = 3, |y| < 3), not through it
    crossing = path[np.argmin(np.abs(path[:, 0] - 3.05))]
    assert abs(crossing[1]) > 2.9


def test_a_growing_3d_map_takes_clouds_anywhere_and_comes_back_the_same(make_client: Any, kit: Any) -> None:
    client = make_client()
    assert client.post("/maps", json={"name": "hall", "resolution": 0.1, "dimensions": 3}).status_code == 201
    for position in ([0.0, 0.0, 1.5], [-40.0, 25.0, -3.0]):
        scan = {"pose": {"position": position, "orientation": [0.0, 0.0, 0.0, 1.0]},
                "points": kit.cloud_sensor_points(distance=2.5).tolist(), "range_max": 10.0}
        assert client.post("/maps/hall/scans", json={"scans": [scan]}).status_code == 200
    info = _info(client, "hall")
    assert info["dimensions"] == 3 and len(info["bounds"]["min"]) == 3
    assert info["bounds"]["min"][2] <= -3.8 and info["bounds"]["max"][2] >= 2.3
    risk = np.load(io.BytesIO(client.get("/maps/hall/risk", params={"format": "npy"}).content))
    assert list(risk.shape) == info["shape"] and info["held_cells"] < risk.size / 4  # the space between is not held
    wall = _query(client, [[-37.45, 25.0 + dy, -3.0 + dz] for dy in np.arange(-1.0, 1.0, 0.1)
                           for dz in np.arange(-0.5, 0.5, 0.1)], name="hall")
    assert max(wall) > 0.5 and _query(client, [[-20.0, 10.0, 0.0]], name="hall") == [0.5]
    again = make_client()
    np.testing.assert_array_equal(
        np.load(io.BytesIO(again.get("/maps/hall/risk", params={"format": "npy"}).content)), risk)


def test_the_ouster_frames_fit_one_growing_map_under_the_default_limits(client: TestClient) -> None:
    # three real OS-1-128 frames at 0.1 m, range_max 30 m, every height: a fixed box over them was refused
    # (64 x 64 x 9 m is already 37 M cells, over the 16 M default)
    assert client.post("/maps", json={"name": "ouster", "resolution": 0.1, "dimensions": 3}).status_code == 201
    for points, rotation, translation in ouster_frames():
        quaternion = Rotation.from_matrix(rotation).as_quat()  # x, y, z, w
        scan = {"pose": {"position": translation.tolist(), "orientation": quaternion.tolist()},
                "points": points.tolist(), "range_max": 30.0}
        response = client.post("/maps/ouster/scans", json={"scans": [scan]})
        assert response.status_code == 200, response.text
    info = _info(client, "ouster")
    assert info["version"] == 3 and 0 < info["held_cells"] <= Settings().max_map_cells
    assert np.prod(info["shape"]) > Settings().max_map_cells  # what a box around the same cells would take


def test_a_growing_map_whose_bounds_pass_the_largest_box_is_read_through_windows(client: TestClient, kit: Any) -> None:
    """Two scans 1.5 km apart: bounds of 225 M cells, a few thousand held. A whole read would copy every cell of the
    bounds (a 500 before, out of memory): refused before any copy, as no fixed map's box is that large."""
    assert client.post("/maps", json=GROWING).status_code == 201
    for x in (0.0, 1500.0):
        assert client.post("/maps/explore/scans", json={"scans": [kit.laser(x=x, y=x)]}).status_code == 200
    info = _info(client)
    assert info["shape"][0] * info["shape"][1] > 64_000_000 and info["held_cells"] < 100_000
    for path in ("risk", "risk.npy", "risk.npy?layer=observed", "risk.png", "occupancy_grid.cdr", "export/nav2",
                 "export/mcap"):
        response = client.get(f"/maps/explore/{path}")
        assert response.status_code == 422 and "read a window" in error_message(response), (path, response.text)
    part = client.get("/maps/explore/risk.npy", params={"min": "1,-2", "max": "5,2"})
    assert part.status_code == 200 and np.load(io.BytesIO(part.content)).max() > 0.5  # the wall at x = 3
    refused = client.post("/maps/explore/plan", json={"start": [0.5, 0.0], "goal": [1500.5, 1500.0],
                                                       "planner": "grid"})
    assert refused.status_code == 413 and "nearer points" in error_message(refused), refused.text
    assert _info(client)["version"] == 2
    # between near points, a plan works on the part of the map around them, and goes around what it saw there
    near = client.post("/maps/explore/plan", json={"start": [2.0, 0.0], "goal": [4.0, 0.0], "planner": "grid",
                                                    "allow_unknown": True})
    assert near.status_code == 200 and near.json()["status"] == "exact", near.text
    path = np.array([[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in near.json()["poses"]])
    assert np.allclose(path[0], [2.0, 0.0], atol=0.1) and np.allclose(path[-1], [4.0, 0.0], atol=0.1)
    assert np.abs(path[np.argmin(np.abs(path[:, 0] - 3.05)), 1]) > 2.9  # the wall at x = 3, |y| < 3


def test_a_plan_on_a_growing_map_is_bounded_as_on_the_fixed_map_of_its_bounds(make_client: Any, kit: Any) -> None:
    """FUZZYRISK_MAX_MAP_CELLS counts what a map holds; a plan's grid is a copy, bounded as a fixed map's box is (64 M
    at least), so a plan across a growing map is answered where one across the fixed map of its bounds is."""
    client = make_client(max_map_cells=20_000)
    assert client.post("/maps", json=GROWING).status_code == 201
    scans = [kit.laser(x=x, y=x) for x in (0.0, 30.0)]
    assert client.post("/maps/explore/scans", json={"scans": scans}).status_code == 200
    info = _info(client)
    assert info["shape"][0] * info["shape"][1] > 20_000 > info["held_cells"]
    box = {"name": "box", "resolution": GROWING["resolution"], "origin": info["origin"], "size": info["size"]}
    assert client.post("/maps", json=box).status_code == 201
    assert client.post("/maps/box/scans", json={"scans": scans}).status_code == 200
    for name in ("box", "explore"):
        plan = client.post(f"/maps/{name}/plan", json={"start": [0.5, 0.0], "goal": [30.5, 30.0], "planner": "grid"})
        assert plan.status_code == 200 and plan.json()["status"] == "exact", (name, plan.text)


def _grid_sources(client: TestClient) -> dict[str, float]:
    text = client.get("/metrics").text
    return {m[1]: float(m[2]) for m in re.finditer(r'^fuzzyrisk_plan_grids_total\{source="(\w+)"\} (\S+)$', text, re.M)}


def test_plans_needing_the_same_window_of_a_version_share_its_published_grid(client: TestClient, kit: Any) -> None:
    assert client.post("/maps", json=GROWING).status_code == 201
    assert client.post("/maps/explore/scans", json={"scans": [kit.laser(wall=3.0)]}).status_code == 200
    request = {"start": [0.5, 0.0], "goal": [2.0, 1.0], "planner": "grid"}
    first, again = (client.post("/maps/explore/plan", json=request) for _ in range(2))
    assert first.status_code == again.status_code == 200, first.text
    assert [p["pose"] for p in first.json()["poses"]] == [p["pose"] for p in again.json()["poses"]]
    sources = _grid_sources(client)
    assert sources.get("published") == 1 and sources.get("shared") == 1  # the second plan copied nothing
    far = client.post("/maps/explore/plan", json={**request, "goal": [12.0, 1.0]})  # past the bounds: its own window
    assert far.status_code == 200, far.text
    assert _grid_sources(client).get("shipped") == 1
