"""``PUT /maps/{name}/trajectory`` and ``GET /maps/{name}/rebuild``: a map fused at drifted poses, corrected by a SLAM
node's trajectory, rebuilt in the background; over HTTP, as a robot's software uses them.

The reference every rebuild is held to is the map fused from scratch at the corrected poses (bit for bit), and the
corrected poses come back from ``GET /maps/{name}/trajectory`` exactly. Batches posted during the rebuild, a superseding
PUT, a restart of the service, and refusals that change nothing. (A kill -9 mid-rebuild: tests/e2e/test_refusion.py;
a fleet: tests/e2e/test_fleet_refusion.py.)
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import psutil
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from app.cli.import_log import scan_json
from app.maps.ingest_process import PROCESS_PARSE_BYTES
from fuzzyocc import LaserScan
from fuzzyocc.carmen import read_carmen
from fuzzyocc.tf import yaw_quaternion
from tests.conftest import DATA_DIR, error_message

S = 10**9
GROWING = {"dimensions": 2, "resolution": 0.1, "model": "fuzzy",
           "sensor": {"range_sigma": 0.03, "registration_sigma": 0.0}}


@pytest.fixture(scope="module")
def log() -> list[LaserScan]:
    """The first 60 scans of a real building's log, with their real stamps."""
    return read_carmen(DATA_DIR / "carmen" / "seattle-corrected.log.gz")[:60]


def drifted(scans: Sequence[LaserScan], seed: int = 5) -> list[LaserScan]:
    """The scans at odometry-like poses: a random walk of 2 % of the distance travelled, 1 degree per metre."""
    rng = np.random.default_rng(seed)
    out, dx, dy, dtheta = [], 0.0, 0.0, 0.0
    for before, scan in zip([scans[0], *scans[:-1]], scans, strict=True):
        step = math.dist(before.pose[:2], scan.pose[:2])
        dx, dy = dx + rng.normal(0.0, 0.02 * step + 1e-3), dy + rng.normal(0.0, 0.02 * step + 1e-3)
        dtheta += rng.normal(0.0, math.radians(1.0) * step + 1e-3)
        x, y, theta = scan.pose
        out.append(dataclasses.replace(scan, pose=(x + dx, y + dy, theta + dtheta)))
    return out


def post_log(client: TestClient, name: str, scans: Sequence[LaserScan], batch: int = 10) -> None:
    for i in range(0, len(scans), batch):
        response = client.post(f"/maps/{name}/scans", json={"scans": [scan_json(s) for s in scans[i:i + batch]]})
        assert response.status_code == 200, response.text


def path_of(scans: Sequence[LaserScan], frame_id: str = "map") -> dict[str, Any]:
    """The scans' poses as a SLAM node publishes them: a nav_msgs/Path, yaw quaternions, the scans' stamps."""
    poses = []
    for scan in scans:
        x, y, theta = scan.pose
        qx, qy, qz, qw = yaw_quaternion(theta)
        assert scan.stamp_ns is not None
        poses.append({"header": {"stamp": {"sec": scan.stamp_ns // S, "nanosec": scan.stamp_ns % S}, "frame_id": frame_id},
                      "pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}})
    return {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": frame_id}, "poses": poses}


def rebuilt(client: TestClient, name: str, correction: str, timeout: float = 120.0) -> dict[str, Any]:
    """Wait for the rebuild of ``correction`` to end (the service's own status), and return it."""
    deadline = time.monotonic() + timeout
    while True:
        status = client.get(f"/maps/{name}/rebuild").json()
        if status["id"] == correction and status["state"] in ("done", "failed"):
            return dict(status)
        assert time.monotonic() < deadline, status
        time.sleep(0.02)


def grid_of(client: TestClient, name: str) -> tuple[bytes, str, str]:
    response = client.get(f"/maps/{name}/risk", params={"format": "npy"})
    assert response.status_code == 200, response.text
    return response.content, response.headers["X-Map-Origin"], response.headers["X-Map-Shape"]


def fresh_map(client: TestClient, name: str, scans: Sequence[LaserScan], batch: int = 10) -> tuple[bytes, str, str]:
    assert client.post("/maps", json={**GROWING, "name": name}).status_code == 201
    post_log(client, name, scans, batch)
    return grid_of(client, name)


def test_a_corrected_trajectory_rebuilds_the_map_fused_at_the_corrected_poses(
        client: TestClient, log: list[LaserScan]) -> None:
    expected = fresh_map(client, "direct", log)
    drifted_grid = fresh_map(client, "robot", drifted(log))
    assert drifted_grid != expected
    before = client.get("/maps/robot").json()["version"]

    response = client.put("/maps/robot/trajectory", json=path_of(log))
    assert response.status_code == 202, response.text
    accepted = response.json()["rebuild"]
    assert accepted["state"] in ("running", "done") and accepted["from_version"] == before
    assert accepted["scans_reposed"] == len(log)
    status = rebuilt(client, "robot", accepted["id"])
    assert status["state"] == "done", status
    assert status["version"] == before + 1 and status["scans_done"] >= len(log) == status["scans_total"]
    assert status["eta_s"] is None and status["error"] is None

    assert client.get("/maps/robot").json()["version"] == before + 1
    assert grid_of(client, "robot") == expected  # bit for bit, origin and shape too
    poses = client.get("/maps/robot/trajectory").json()["poses"]
    assert poses == path_of(log)["poses"]  # the corrected poses, exactly, with the scans' stamps
    last = client.get("/maps/robot/scans/last").json()
    assert last["version"] == before + 1 and last["origin"] == list(log[-1].pose[:2])  # the last scan, corrected


def test_scans_outside_the_paths_range_keep_their_poses_and_an_offset_places_the_sensor(
        client: TestClient, log: list[LaserScan]) -> None:
    # the robot's path (base_link) for the middle 20 scans; the laser sits 0.3 m ahead of base_link, turned by 90 deg
    offset_q = yaw_quaternion(math.pi / 2)
    robot = []
    for scan in log[20:40]:
        x, y, theta = scan.pose
        base_theta = theta - math.pi / 2
        robot.append(dataclasses.replace(scan, pose=(x - 0.3 * math.cos(base_theta), y - 0.3 * math.sin(base_theta),
                                                     base_theta)))
    moved = drifted(log)
    fresh_map(client, "robot", moved)
    response = client.put("/maps/robot/trajectory", json=path_of(robot),
                          params={"offset_x": 0.3, "offset_qz": offset_q[2], "offset_qw": offset_q[3]})
    assert response.status_code == 202, response.text
    assert response.json()["rebuild"]["scans_reposed"] == 20
    assert rebuilt(client, "robot", response.json()["rebuild"]["id"])["state"] == "done"
    got = client.get("/maps/robot/trajectory").json()["poses"]
    for i, pose in enumerate(got):
        want = log[i].pose if 20 <= i < 40 else moved[i].pose
        position, q = pose["pose"]["position"], pose["pose"]["orientation"]
        assert (position["x"], position["y"]) == pytest.approx(want[:2], abs=1e-9)
        yaw = 2.0 * math.atan2(q["z"], q["w"])
        assert math.remainder(yaw - want[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
        if not 20 <= i < 40:
            assert (position["x"], position["y"]) == want[:2]  # untouched: exactly as posted


def test_batches_posted_during_the_rebuild_reach_the_rebuilt_map_in_their_order(
        client: TestClient, log: list[LaserScan]) -> None:
    history, later = log[:40], log[40:]
    expected = fresh_map(client, "direct", [*history, *later], batch=5)
    fresh_map(client, "robot", drifted(history), batch=5)
    response = client.put("/maps/robot/trajectory", json=path_of(history))
    assert response.status_code == 202, response.text
    post_log(client, "robot", later, batch=5)  # while the rebuild runs, or after it: the map must end the same
    assert rebuilt(client, "robot", response.json()["rebuild"]["id"])["state"] == "done"
    assert grid_of(client, "robot") == expected
    assert client.get("/maps/robot").json()["version"] == client.get("/maps/direct").json()["version"] + 1


def test_a_second_correction_supersedes_the_first_and_the_latest_wins(
        client: TestClient, log: list[LaserScan]) -> None:
    expected = fresh_map(client, "direct", log)
    fresh_map(client, "robot", drifted(log))
    first = client.put("/maps/robot/trajectory", json=path_of(drifted(log, seed=9)))
    second = client.put("/maps/robot/trajectory", json=path_of(log))
    assert first.status_code == second.status_code == 202
    status = rebuilt(client, "robot", second.json()["rebuild"]["id"])
    assert status["state"] == "done" and status["id"] != first.json()["rebuild"]["id"]
    assert grid_of(client, "robot") == expected


def test_a_restart_serves_the_rebuilt_map_and_its_corrected_trajectory(
        make_client: Callable[..., TestClient], log: list[LaserScan]) -> None:
    client = make_client()
    expected = fresh_map(client, "direct", log)
    fresh_map(client, "robot", drifted(log))
    response = client.put("/maps/robot/trajectory", json=path_of(log))
    assert rebuilt(client, "robot", response.json()["rebuild"]["id"])["state"] == "done"
    trajectory = client.get("/maps/robot/trajectory").json()
    client.__exit__(None, None, None)
    again = make_client()
    assert grid_of(again, "robot") == expected
    assert again.get("/maps/robot/trajectory").json()["poses"] == trajectory["poses"]
    assert again.get("/maps/robot/rebuild").json()["state"] == "done"


def _shifted(path: dict[str, Any], **change: Any) -> dict[str, Any]:
    out = {"header": dict(path["header"]), "poses": [dict(p) for p in path["poses"]]}
    out.update(change)
    return out


@pytest.mark.parametrize(("mutate", "status", "words"), [
    (lambda p: _shifted(p, header={"stamp": {"sec": 0, "nanosec": 0}, "frame_id": "odom"}), 422, "header.frame_id"),
    (lambda p: _shifted(p, poses=[p["poses"][1], p["poses"][0], *p["poses"][2:]]), 422, "poses[1].header.stamp"),
    (lambda p: _shifted(p, poses=[p["poses"][0], {**p["poses"][1], "pose": {
        "position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 2.0}}}]),
     422, "poses[1].pose.orientation"),
    (lambda p: _shifted(p, poses=[{**p["poses"][0], "header": {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": "map"}},
                                  {**p["poses"][1], "header": {"stamp": {"sec": 2, "nanosec": 0}, "frame_id": "map"}}]),
     409, "no stored scan has a stamp in the trajectory's range"),
    (lambda p: _shifted(p, poses=[]), 422, "poses"),
    (lambda p: _shifted(p, poses=[p["poses"][0], {**p["poses"][1], "pose": {
        "position": {"x": 0.0, "y": 0.0, "z": 0.0},
        "orientation": {"x": math.sin(math.radians(5)), "y": 0.0, "z": 0.0, "w": math.cos(math.radians(5))}}}]),
     422, "tilted 10.0 degrees"),
])
def test_a_refused_correction_names_its_field_and_changes_nothing(
        client: TestClient, log: list[LaserScan], mutate: Callable[[dict[str, Any]], dict[str, Any]], status: int,
        words: str) -> None:
    before = fresh_map(client, "robot", log[:20])
    version = client.get("/maps/robot").json()["version"]
    response = client.put("/maps/robot/trajectory", json=mutate(path_of(log[:20])))
    assert response.status_code == status, response.text
    assert words in error_message(response) or words in response.text
    assert client.get("/maps/robot/rebuild").json() == {**client.get("/maps/robot/rebuild").json(), "state": "none"}
    assert grid_of(client, "robot") == before and client.get("/maps/robot").json()["version"] == version


def test_not_a_number_and_too_many_poses_are_refused(make_client: Callable[..., TestClient],
                                                     log: list[LaserScan]) -> None:
    client = make_client(max_trajectory_poses=10)
    fresh_map(client, "robot", log[:20])
    body = path_of(log[:5])
    body["poses"][2]["pose"]["position"]["x"] = math.nan
    response = client.put("/maps/robot/trajectory", content=json.dumps(body),
                          headers={"Content-Type": "application/json"})
    assert response.status_code == 422 and "poses" in response.text
    response = client.put("/maps/robot/trajectory", json=path_of(log[:20]))
    assert response.status_code == 413 and "FUZZYRISK_MAX_TRAJECTORY_POSES" in error_message(response)
    assert client.get("/maps/robot/rebuild").json()["state"] == "none"
    assert client.put("/maps/nowhere/trajectory", json=path_of(log[:5])).status_code == 404
    assert client.get("/maps/nowhere/rebuild").status_code == 404


def _padded(path: dict[str, Any], poses: int) -> dict[str, Any]:
    """``path`` followed by ``poses`` more, a second apart after its last stamp (no stored scan there): a body past
    ``PROCESS_PARSE_BYTES``."""
    last = path["poses"][-1]
    sec = last["header"]["stamp"]["sec"]
    extra = [{**last, "header": {**last["header"], "stamp": {"sec": sec + 1 + i, "nanosec": 0}}} for i in range(poses)]
    return _shifted(path, poses=[*path["poses"], *extra])


def test_a_large_corrected_trajectory_is_read_in_the_parse_process_as_a_small_one_is(
        make_client: Callable[..., TestClient], log: list[LaserScan]) -> None:
    client = make_client(max_trajectory_poses=2_000)
    expected = fresh_map(client, "direct", log)
    fresh_map(client, "robot", drifted(log))
    version = client.get("/maps/robot").json()["version"]
    large = _padded(path_of(log), 1_800)
    assert len(json.dumps(large)) > PROCESS_PARSE_BYTES
    # refused as in a parse thread, naming the field; nothing changes
    unordered = _shifted(large, poses=[*large["poses"][:1500], large["poses"][1501], large["poses"][1500],
                                       *large["poses"][1502:]])
    response = client.put("/maps/robot/trajectory", json=unordered)
    assert response.status_code == 422 and "poses[1501].header.stamp" in error_message(response), response.text
    response = client.put("/maps/robot/trajectory", json=_padded(path_of(log), 2_000))
    assert response.status_code == 413 and "FUZZYRISK_MAX_TRAJECTORY_POSES" in error_message(response)
    response = client.put("/maps/robot/trajectory", content=json.dumps(large)[:-2],
                          headers={"Content-Type": "application/json"})
    assert response.status_code == 422 and response.json()["code"] == "VALIDATION_ERROR", response.text
    assert client.get("/maps/robot/rebuild").json()["state"] == "none"
    assert client.get("/maps/robot").json()["version"] == version
    # and taken: the same rebuilt map as a path of the scans' poses alone
    response = client.put("/maps/robot/trajectory", json=large)
    assert response.status_code == 202, response.text
    assert rebuilt(client, "robot", response.json()["rebuild"]["id"])["state"] == "done"
    assert grid_of(client, "robot") == expected
    executor = client.app.state.service.writes.parse_process._executor  # type: ignore[attr-defined]
    assert executor is not None and [psutil.Process(p.pid).is_running() for p in executor._processes.values()] == [True]


@pytest.fixture
def held_rebuild(monkeypatch: pytest.MonkeyPatch) -> threading.Event:
    """Rebuilds wait (in their fusion thread, still stoppable) until the event is set: the test sees the map while
    one runs."""
    from app.maps import refusion

    release = threading.Event()
    restore = refusion.restore

    def held(stored: Any, up_to: Any = None, progress: Any = None) -> Any:
        while not release.wait(0.01):
            progress(0)  # a superseded or stopped rebuild still stops here
        return restore(stored, up_to, progress)

    monkeypatch.setattr(refusion, "restore", held)
    return release


def test_reads_are_the_current_maps_until_the_rebuilt_one_replaces_it_whole(
        client: TestClient, log: list[LaserScan], held_rebuild: threading.Event) -> None:
    history, later = log[:40], log[40:]
    expected = fresh_map(client, "direct", [*history, *later], batch=5)
    drifted_grid = fresh_map(client, "robot", drifted(history), batch=5)
    response = client.put("/maps/robot/trajectory", json=path_of(history))
    correction = response.json()["rebuild"]["id"]
    assert client.get("/maps/robot/rebuild").json()["state"] == "running"
    assert grid_of(client, "robot") == drifted_grid  # the current map, not a half-built one
    post_log(client, "robot", later, batch=5)  # these reach the rebuilt map from the store, before the switch
    live = fresh_map(client, "live", [*drifted(history), *later], batch=5)
    assert grid_of(client, "robot") == live
    assert client.get("/maps/robot/rebuild").json()["state"] == "running"
    held_rebuild.set()
    assert rebuilt(client, "robot", correction)["state"] == "done"
    assert grid_of(client, "robot") == expected


def test_a_rebuild_stopped_by_a_restart_resumes_and_completes(
        make_client: Callable[..., TestClient], log: list[LaserScan], held_rebuild: threading.Event) -> None:
    client = make_client(rebuild_lease_s=1.0)
    expected = fresh_map(client, "direct", log)
    drifted_grid = fresh_map(client, "robot", drifted(log))
    correction = client.put("/maps/robot/trajectory", json=path_of(log)).json()["rebuild"]["id"]
    client.__exit__(None, None, None)  # the rebuild stops with the service; its correction stays pending
    again = make_client(rebuild_lease_s=1.0)
    assert grid_of(again, "robot") == drifted_grid
    assert again.get("/maps/robot/rebuild").json()["state"] == "running"
    held_rebuild.set()
    status = rebuilt(again, "robot", correction)
    assert status["state"] == "done" and grid_of(again, "robot") == expected


def _clouds(kit: Any, poses: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[dict[str, Any]]:
    points = kit.cloud_sensor_points().tolist()
    return [{"pose": {"position": position.tolist(), "orientation": quaternion.tolist()}, "points": points,
             "range_max": 10.0, "header": {"stamp": {"sec": 100 + k, "nanosec": 0}, "frame_id": "laser"}}
            for k, (position, quaternion) in enumerate(poses)]


def test_a_map_of_3d_clouds_is_rebuilt_at_the_corrected_sensor_poses(client: TestClient, kit: Any) -> None:
    # a 3-D sensor takes the whole corrected pose: position and orientation, roll and pitch included
    rng = np.random.default_rng(4)
    true = [(np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 1.0 + rng.uniform(-0.2, 0.2)]),
             Rotation.from_euler("zyx", [rng.uniform(-3, 3), rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)]).as_quat())
            for _ in range(12)]
    drift = [(p + rng.normal(0, 0.1, 3), (Rotation.from_quat(q) * Rotation.from_euler("z", rng.normal(0, 0.05))).as_quat())
             for p, q in true]
    for name, poses in (("direct", true), ("robot", drift)):
        assert client.post("/maps", json={**kit.MAP_3D, "name": name}).status_code == 201
        assert client.post(f"/maps/{name}/scans", json={"scans": _clouds(kit, poses)}).status_code == 200
    assert grid_of(client, "robot") != grid_of(client, "direct")
    path = {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": "map"},
            "poses": [{"header": {"stamp": {"sec": 100 + k, "nanosec": 0}, "frame_id": "map"},
                       "pose": {"position": dict(zip("xyz", p.tolist(), strict=True)),
                                "orientation": dict(zip("xyzw", q.tolist(), strict=True))}}
                      for k, (p, q) in enumerate(true)]}
    response = client.put("/maps/robot/trajectory", json=path)
    assert response.status_code == 202, response.text
    assert response.json()["rebuild"]["scans_reposed"] == len(true)
    assert rebuilt(client, "robot", response.json()["rebuild"]["id"])["state"] == "done"
    assert grid_of(client, "robot") == grid_of(client, "direct")
    # the trajectory gives each cloud's sensor pose, orientation included
    assert client.get("/maps/robot/trajectory").json()["poses"] == path["poses"]


def _history(client: TestClient, name: str, scans: Sequence[LaserScan]) -> None:
    """Scans, a region cleared, forgetting changed, more scans: a history of every kind of batch, in order."""
    post_log(client, name, scans[:25])
    assert client.post(f"/maps/{name}/clear", json={"min": [0.0, -1.0], "max": [2.0, 1.0]}).status_code == 200
    if client.get(f"/maps/{name}").json()["extent"] == "growing":
        assert client.patch(f"/maps/{name}", json={"forget_beyond": 6.0}).status_code == 200
    post_log(client, name, scans[25:])


def test_the_rebuild_replays_priors_clears_and_forgetting_in_their_place(
        client: TestClient, log: list[LaserScan]) -> None:
    # a saved map to start from: the building's first scans, as a Nav2 user would have it
    fresh_map(client, "survey", log[:15])
    saved = client.get("/maps/survey/occupancy_grid").json()
    for name, scans in (("direct", log), ("robot", drifted(log))):
        assert client.post("/maps/import", params={"name": name}, json=saved).status_code == 201
        _history(client, name, scans)
        assert client.post("/maps", json={**GROWING, "name": f"{name}-growing", "forget_beyond": 8.0}
                           ).status_code == 201
        _history(client, f"{name}-growing", scans)
    for name in ("robot", "robot-growing"):
        response = client.put(f"/maps/{name}/trajectory", json=path_of(log))
        assert response.status_code == 202, response.text
        assert rebuilt(client, name, response.json()["rebuild"]["id"])["state"] == "done"
    assert grid_of(client, "robot") == grid_of(client, "direct")  # the prior as imported, the clear in its place
    assert grid_of(client, "robot-growing") == grid_of(client, "direct-growing")  # forgetting at the new poses
