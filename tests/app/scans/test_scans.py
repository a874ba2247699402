"""Scan batches: JSON and binary uploads, REP 117 ranges, and every kind of bad input (4xx, nothing changed)."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from tests.conftest import error_message

JSON = {"Content-Type": "application/json"}
NPY = {"Content-Type": "application/x-npy"}
RAW = {"Content-Type": "application/octet-stream"}


def risk_at(client: TestClient, name: str, points: list[list[float]]) -> list[float]:
    response = client.post(f"/maps/{name}/risk/query", json={"points": points})
    assert response.status_code == 200, response.text
    return response.json()["risk"]


def test_a_batch_answers_its_counts_and_the_new_version(lab: TestClient, kit: Any) -> None:
    response = lab.post("/maps/lab/scans", json={"scans": [kit.laser(beams=90), kit.laser(beams=45)]})
    assert response.status_code == 200
    body = response.json()
    assert body["scans_fused"] == 2 and body["rays"] == 135 and body["version"] == 1
    assert body["cells_updated"] > 135
    info = lab.get("/maps/lab").json()
    assert info["version"] == 1 and info["scans_fused"] == 2 and info["updated"] >= info["created"]  # same millisecond is possible


def test_a_scan_makes_the_wall_risky_and_the_space_before_it_safe(lab: TestClient, kit: Any) -> None:
    lab.post("/maps/lab/scans", json={"scans": [kit.laser(wall=3.05)]})
    before, wall, behind = risk_at(lab, "lab", [[1.5, 0.0], [3.05, 0.0], [4.5, 0.0]])
    # one scan is one level of evidence: free below unknown, the wall above the default max_risk
    assert before < 0.5 and wall > 0.6
    assert behind == 0.5  # never reached: unknown


def test_each_batch_adds_one_version(lab: TestClient, kit: Any) -> None:
    versions = [lab.post("/maps/lab/scans", json={"scans": [kit.laser()]}).json()["version"] for _ in range(4)]
    assert versions == [1, 2, 3, 4]


def _fused_risk(client: TestClient, kit: Any, name: str, ranges: list[Any]) -> np.ndarray:
    client.post("/maps", json={**kit.MAP_2D, "name": name})
    body = json.dumps({"scans": [kit.laser(beams=len(ranges), ranges=ranges)]})
    response = client.post(f"/maps/{name}/scans", content=body, headers=JSON)
    assert response.status_code == 200, response.text
    return kit.risk_npy(client, name)


def test_rep117_no_return_tokens_clear_free_space_like_a_legacy_range_max(client: TestClient, kit: Any) -> None:
    base = kit.laser(beams=9)["ranges"]
    legacy = _fused_risk(client, kit, "legacy", base[:4] + [21.0] + base[5:])  # range_max + 1: no return
    for i, token in enumerate(["inf", "+inf", "Infinity"]):
        assert np.array_equal(_fused_risk(client, kit, f"tok{i}", base[:4] + [token] + base[5:]), legacy), token
    # the non-standard JSON token that Python's json.dumps writes
    raw = json.dumps({"scans": [kit.laser(beams=9, ranges=base[:4] + [math.inf] + base[5:])]})
    client.post("/maps", json={**kit.MAP_2D, "name": "pyjson"})
    assert "Infinity" in raw and client.post("/maps/pyjson/scans", content=raw, headers=JSON).status_code == 200
    assert np.array_equal(kit.risk_npy(client, "pyjson"), legacy)


def test_rep117_invalid_readings_are_skipped(client: TestClient, kit: Any) -> None:
    base = kit.laser(beams=9)["ranges"]
    too_close = _fused_risk(client, kit, "close", base[:4] + [0.05] + base[5:])  # below range_min: skipped
    for i, token in enumerate([None, "nan", "NaN", "-inf", "-Infinity"]):
        assert np.array_equal(_fused_risk(client, kit, f"skip{i}", base[:4] + [token] + base[5:]), too_close), token
    assert not np.array_equal(too_close, _fused_risk(client, kit, "full", base))


# ---------------------------------------------------------------- bad input: 4xx, and nothing changes


def _assert_refused(client: TestClient, kit: Any, name: str, body: Any, status: int, needle: str,
                    headers: dict[str, str] | None = None, params: dict[str, Any] | None = None) -> None:
    before_version, before_risk = kit.version(client, name), kit.risk_npy(client, name)
    content = body if isinstance(body, (bytes, str)) else json.dumps(body)
    response = client.post(f"/maps/{name}/scans", content=content, headers=headers or JSON, params=params)
    assert response.status_code == status, response.text
    assert needle in json.dumps(response.json()), response.json()
    assert kit.version(client, name) == before_version
    assert np.array_equal(kit.risk_npy(client, name), before_risk)
    assert client.get(f"/maps/{name}").json()["scans_fused"] == 0


def _with(scan: dict[str, Any], **change: Any) -> dict[str, Any]:
    return {**scan, **change}


BAD_LASER_BATCHES = [
    pytest.param(lambda k: {"scans": []}, "scans", id="empty-batch"),
    pytest.param(lambda k: {"scans": [{"pose": {"x": 0, "y": 0, "theta": 0}}]}, "ranges", id="neither-ranges-nor-points"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), pose={"x": 0, "y": 0})]}, "theta", id="pose-without-theta"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), pose={"x": 0, "y": 0, "theta": "NaN"})]}, "theta", id="pose-nan-string"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), angle_increment=0.0)]}, "angle_increment", id="zero-increment"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), range_min=5.0, range_max=4.0)]}, "range_max", id="range-max-below-min"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), range_max=0.0)]}, "range_max", id="range-max-zero"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), ranges=[])]}, "ranges", id="no-ranges"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), ranges=[1.0, "far"])]}, "ranges", id="range-word"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), registration_sigma=-1)]}, "registration_sigma", id="negative-sigma"),
    pytest.param(lambda k: {"scans": [_with(k.laser(), rangez=[1.0])]}, "rangez", id="unknown-field"),
    pytest.param(lambda k: {"scans": [k.laser(), _with(k.laser(), angle_increment=0.0)]}, "scans[1]", id="second-scan-bad"),
    pytest.param(
        lambda k: {"scans": [{"pose": {"x": 0, "y": 0, "theta": 0}, "points": [[1, 2, 3]], "range_max": 9}]},
        "points", id="3d-points-on-2d-map",
    ),
    pytest.param(
        lambda k: {"scans": [{"pose": {"x": 0, "y": 0, "theta": 0}, "points": [[1, 2], [1, 2, 3]], "range_max": 9}]},
        "points", id="ragged-points",
    ),
    pytest.param(
        lambda k: {"scans": [{"pose": {"position": [0, 0, 0], "orientation": [0, 0, 0, 1]}, "points": [[1, 2]],
                              "range_max": 9}]},
        "pose", id="3d-pose-on-2d-map",
    ),
]


@pytest.mark.parametrize(("make_body", "needle"), BAD_LASER_BATCHES)
def test_bad_batches_answer_422_and_change_nothing(lab: TestClient, kit: Any, make_body: Any, needle: str) -> None:
    _assert_refused(lab, kit, "lab", make_body(kit), 422, needle)


def test_a_pose_with_a_nan_token_is_refused(lab: TestClient, kit: Any) -> None:
    body = json.dumps({"scans": [kit.laser()]}).replace('"theta": 0.0', '"theta": NaN')
    assert "NaN" in body
    _assert_refused(lab, kit, "lab", body, 422, "theta")


def test_malformed_json_answers_422(lab: TestClient, kit: Any) -> None:
    _assert_refused(lab, kit, "lab", '{"scans": [', 422, "json")


def test_other_content_types_answer_415(lab: TestClient, kit: Any) -> None:
    _assert_refused(lab, kit, "lab", json.dumps({"scans": [kit.laser()]}), 415, "application/json",
                    headers={"Content-Type": "text/plain"})


def test_batches_over_the_scan_limit_answer_413(make_client: Any, kit: Any) -> None:
    client = make_client(max_scans_per_batch=2)
    client.post("/maps", json=kit.MAP_2D)
    _assert_refused(client, kit, "lab", {"scans": [kit.laser()] * 3}, 413, "FUZZYRISK_MAX_SCANS_PER_BATCH")
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()] * 2}).status_code == 200


def test_scans_over_the_beam_limit_answer_413(make_client: Any, kit: Any) -> None:
    client = make_client(max_rays_per_scan=50)
    client.post("/maps", json=kit.MAP_2D)
    _assert_refused(client, kit, "lab", {"scans": [kit.laser(beams=51)]}, 413, "FUZZYRISK_MAX_RAYS_PER_SCAN")
    laser_query = {"x": 0, "y": 0, "theta": 0, "angle_min": -1, "angle_increment": 0.01, "range_min": 0.1,
                   "range_max": 9}
    _assert_refused(client, kit, "lab", np.ones(51, dtype="<f4").tobytes(), 413, "FUZZYRISK_MAX_RAYS_PER_SCAN",
                    headers=RAW, params=laser_query)


def test_a_laser_scan_on_a_3d_map_is_refused(client: TestClient, kit: Any) -> None:
    client.post("/maps", json=kit.MAP_3D)
    _assert_refused(client, kit, "hall", {"scans": [kit.laser()]}, 422, "3-D")


def test_a_quaternion_that_is_not_unit_is_refused(client: TestClient, kit: Any) -> None:
    client.post("/maps", json=kit.MAP_3D)
    scan = {"pose": {"position": [0, 0, 1], "orientation": [0, 0, 0, 2]}, "points": [[1, 0, 0]], "range_max": 9}
    _assert_refused(client, kit, "hall", {"scans": [scan]}, 422, "unit quaternion")


# ---------------------------------------------------------------- point clouds and the binary path


def _cloud_json(points: np.ndarray, position: list[float], orientation: list[float]) -> dict[str, Any]:
    return {"scans": [{"pose": {"position": position, "orientation": orientation}, "points": points.tolist(),
                       "range_max": 10.0}]}


def test_a_3d_cloud_marks_its_wall_in_the_map_frame(client: TestClient, kit: Any) -> None:
    client.post("/maps", json=kit.MAP_3D)
    yaw90 = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]  # sensor x axis -> map y axis
    response = client.post("/maps/hall/scans", json=_cloud_json(kit.cloud_sensor_points(), [0.0, 0.0, 1.5], yaw90))
    assert response.status_code == 200 and response.json()["rays"] == 200
    before, wall = risk_at(client, "hall", [[0.0, 1.2, 1.5], [0.1, 2.5, 1.5]])
    assert before < 0.5 and wall > 0.6  # one level of evidence each way


def test_binary_npy_points_fuse_exactly_like_the_same_json(client: TestClient, kit: Any) -> None:
    points = kit.cloud_sensor_points()
    pose = {"x": 0.5, "y": -0.5, "z": 1.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0, "range_max": 10.0}
    client.post("/maps", json=kit.MAP_3D)
    client.post("/maps", json={**kit.MAP_3D, "name": "hall_bin"})
    client.post("/maps/hall/scans", json=_cloud_json(points, [0.5, -0.5, 1.0], [0, 0, 0, 1]))
    response = client.post("/maps/hall_bin/scans", params=pose, content=kit.npy(points), headers=NPY)
    assert response.status_code == 200, response.text
    assert np.array_equal(kit.risk_npy(client, "hall_bin"), kit.risk_npy(client, "hall"))


def test_binary_raw_float32_points_equal_json_of_the_same_float32_values(client: TestClient, kit: Any) -> None:
    points32 = kit.cloud_sensor_points().astype(np.float32)
    client.post("/maps", json=kit.MAP_3D)
    client.post("/maps", json={**kit.MAP_3D, "name": "hall_raw"})
    client.post("/maps/hall/scans", json=_cloud_json(points32.astype(np.float64), [0, 0, 1], [0, 0, 0, 1]))
    # orientation defaults to identity; point_step states the layout (packed x y z float32)
    params = {"x": 0, "y": 0, "z": 1, "range_max": 10.0, "point_step": 12}
    response = client.post("/maps/hall_raw/scans", params=params, content=points32.astype("<f4").tobytes(), headers=RAW)
    assert response.status_code == 200, response.text
    assert np.array_equal(kit.risk_npy(client, "hall_raw"), kit.risk_npy(client, "hall"))


def test_binary_raw_laser_ranges_equal_the_json_scan(client: TestClient, kit: Any) -> None:
    scan = kit.laser(x=0.2, y=-0.3, theta=0.4)
    ranges32 = np.array(scan["ranges"], dtype=np.float32)
    ranges32[3] = np.inf
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps", json={**kit.MAP_2D, "name": "lab_raw"})
    json_ranges = [("inf" if math.isinf(r) else float(r)) for r in ranges32.astype(np.float64)]
    assert client.post("/maps/lab/scans", json={"scans": [{**scan, "ranges": json_ranges}]}).status_code == 200
    params = {"x": 0.2, "y": -0.3, "theta": 0.4, "angle_min": scan["angle_min"],
              "angle_increment": scan["angle_increment"], "range_min": 0.1, "range_max": 20.0}
    response = client.post("/maps/lab_raw/scans", params=params, content=ranges32.astype("<f4").tobytes(), headers=RAW)
    assert response.status_code == 200, response.text
    assert np.array_equal(kit.risk_npy(client, "lab_raw"), kit.risk_npy(client, "lab"))


def test_a_2d_cloud_is_placed_by_its_planar_pose(lab: TestClient) -> None:
    scan = {"pose": {"x": 1.0, "y": 0.0, "theta": math.pi / 2}, "points": [[2.05, dy] for dy in (-0.2, 0.0, 0.2)],
            "range_max": 9.0}
    assert lab.post("/maps/lab/scans", json={"scans": [scan]}).status_code == 200
    (at_point,) = risk_at(lab, "lab", [[1.0, 2.05]])  # sensor x axis points along map y
    assert at_point > 0.6


def test_cloud_rows_holding_nan_are_dropped_as_no_returns(client: TestClient, kit: Any) -> None:
    client.post("/maps", json=kit.MAP_3D)
    points = kit.cloud_sensor_points(10).tolist()
    points[3] = [None, None, None]
    response = client.post("/maps/hall/scans", json={"scans": [{"pose": {"position": [0, 0, 1], "orientation": [0, 0, 0, 1]},
                                                                 "points": points, "range_max": 10}]})
    assert response.status_code == 200 and response.json()["rays"] == 9


@pytest.mark.parametrize(
    ("body", "params", "needle"),
    [
        (np.zeros((5, 3)), {"x": 0, "y": 0, "range_max": 5}, "z"),  # z missing
        (np.zeros((5, 2)), {"x": 0, "y": 0, "z": 1, "range_max": 5}, "(N, 3)"),
        (np.zeros((5, 3), dtype=np.int32), {"x": 0, "y": 0, "z": 1, "range_max": 5}, "float32 or float64"),
        (b"\x00" * 10, {"x": 0, "y": 0, "z": 1, "range_max": 5}, "float32"),
        (b"\x00" * 16, {"x": 0, "y": 0, "z": 1, "range_max": 5, "point_step": 12}, "whole number of points"),
        (b"", {"x": 0, "y": 0, "z": 1, "range_max": 5}, "empty"),
        (np.zeros((5, 3)), {"x": 0, "y": 0, "z": 1, "range_max": 5, "qw": 3}, "unit quaternion"),
        (np.zeros((5, 3)), {"x": "nan", "y": 0, "z": 1, "range_max": 5}, "x"),
    ],
    ids=["missing-z", "wrong-columns", "int-dtype", "ragged-raw", "raw-not-xyz", "empty", "bad-quaternion", "nan-pose"],
)
def test_bad_binary_uploads_answer_422_and_change_nothing(client: TestClient, kit: Any, body: Any, params: dict,
                                                          needle: str) -> None:
    client.post("/maps", json=kit.MAP_3D)
    content = kit.npy(body) if isinstance(body, np.ndarray) else body
    before = kit.risk_npy(client, "hall")
    response = client.post("/maps/hall/scans", params=params, content=content, headers=NPY)
    assert response.status_code == 422, response.text
    assert needle in json.dumps(response.json())
    assert kit.version(client, "hall") == 0 and np.array_equal(kit.risk_npy(client, "hall"), before)


def test_a_pickled_npy_is_never_unpickled(client: TestClient, kit: Any) -> None:
    client.post("/maps", json=kit.MAP_3D)
    evil = kit.npy(np.array([{"a": 1}], dtype=object))  # np.save pickles object arrays
    response = client.post("/maps/hall/scans", params={"x": 0, "y": 0, "z": 1, "range_max": 5}, content=evil,
                           headers=NPY)
    assert response.status_code == 422
    assert kit.version(client, "hall") == 0


def test_a_binary_laser_scan_needs_its_angles(lab: TestClient) -> None:
    response = lab.post("/maps/lab/scans", params={"x": 0, "y": 0, "theta": 0, "range_max": 5},
                        content=np.ones(10, dtype="<f4").tobytes(), headers=RAW)
    assert response.status_code == 422
    assert "angle_min" in error_message(response) and "angle_increment" in error_message(response)


# ---------------------------------------------------------------- the last scan


def test_last_scan_is_404_before_any_scan_then_shows_beam_ends(lab: TestClient, kit: Any) -> None:
    assert lab.get("/maps/lab/scans/last").status_code == 404
    ranges = kit.laser(beams=5)["ranges"]
    ranges[2] = "inf"
    ranges[4] = None
    lab.post("/maps/lab/scans", json={"scans": [kit.laser(x=1.0, y=2.0, beams=5, ranges=ranges)]})
    last = lab.get("/maps/lab/scans/last").json()
    assert last["origin"] == [1.0, 2.0] and last["version"] == 1
    assert last["hit"] == [True, True, False, True]  # the null beam is skipped
    no_return = np.array(last["endpoints"][2])
    assert np.hypot(*(no_return - [1.0, 2.0])) == pytest.approx(20.0, abs=1e-3)  # drawn at range_max
    assert last["endpoints"][0] == pytest.approx([1.0 + 3.0, 2.0 - 3.0], abs=1e-3)  # -45 degrees, wall at 3 m


def test_last_scan_is_thinned_to_4096_beams(lab: TestClient, kit: Any) -> None:
    lab.post("/maps/lab/scans", json={"scans": [kit.laser(beams=10_000)]})
    last = lab.get("/maps/lab/scans/last").json()
    assert 2048 < len(last["endpoints"]) <= 4096 and len(last["hit"]) == len(last["endpoints"])


def test_a_3d_cloud_sent_to_a_2d_map_is_told_it_needs_a_3d_map(lab: TestClient) -> None:
    cloud = {"pose": {"position": [0.0, 0.0, 1.0], "orientation": [0, 0, 0, 1]}, "points": [[1.0, 0.0, 0.0]],
             "range_max": 5.0}
    answer = lab.post("/maps/lab/scans", json={"scans": [cloud]})
    assert answer.status_code == 422 and "dimensions 3" in answer.text and "{x, y, theta}" in answer.text
    assert lab.get("/maps/lab").json()["version"] == 0


def test_a_single_beam_rangefinder_needs_no_angle_increment(lab: TestClient, kit: Any) -> None:
    beam = {**kit.laser(ranges=[2.0]), "angle_min": 0.0, "angle_increment": 0.0}
    assert lab.post("/maps/lab/scans", json={"scans": [beam]}).json()["version"] == 1
    risk = lab.post("/maps/lab/risk/query", json={"points": [[1.0, 0.0], [2.05, 0.0]]}).json()["risk"]
    assert risk[0] < 0.5 and risk[1] > 0.6  # free before the hit, occupied at it
    two = {**kit.laser(ranges=[2.0, 2.0]), "angle_increment": 0.0}
    answer = lab.post("/maps/lab/scans", json={"scans": [two]})
    assert answer.status_code == 422 and "angle_increment" in answer.text


def test_a_scan_whose_angles_overflow_is_refused_and_nothing_is_stored(lab: TestClient, kit: Any) -> None:
    # angle_increment 1e308 is finite, but the beams' angles overflow: the cast wrote outside the map (a
    # segfault, replayed at every restart) before this check
    body = {"scans": [{**kit.laser(beams=5000), "angle_increment": 1e308}]}
    refused = lab.post("/maps/lab/scans", json=body)
    assert refused.status_code == 422 and "angles" in error_message(refused)
    assert kit.version(lab, "lab") == 0
