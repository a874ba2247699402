"""A scan's stamp in, and ``GET /maps/{name}/trajectory`` out: over HTTP, as a robot's software uses them.

Stamps posted as JSON ``header.stamp``, with CDR messages and in bags come back with the poses the scans were posted
with; a scan without one is stamped when the service received it; a restart gives the same trajectory (after a kill
-9 too: ``tests/e2e/test_durability.py``); bad stamps are refused and nothing is stored; a store written before
stamps reads as unstamped.
"""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from app.storage.backup import DATABASE
from tests.app._ros import CLOUD_CT, LASER_CT, cdr, cloud_msg, laser_msg, wall_ranges
from tests.conftest import DATA_DIR, error_message

S = 10**9


def stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // S, "nanosec": ns % S}


def ns_of(pose: dict[str, Any]) -> int:
    return int(pose["header"]["stamp"]["sec"]) * S + int(pose["header"]["stamp"]["nanosec"])


def trajectory(client: TestClient, name: str) -> dict[str, Any]:
    response = client.get(f"/maps/{name}/trajectory")
    assert response.status_code == 200, response.text
    body = response.json()
    assert response.headers["X-Map-Version"] == str(body["version"])
    return dict(body)


def yaw_of(orientation: dict[str, float]) -> float:
    return float(Rotation.from_quat([orientation[k] for k in "xyzw"]).as_euler("zyx")[0])


def test_json_stamps_come_back_with_the_poses_in_the_order_fused(lab: TestClient, kit: Any) -> None:
    first = [kit.laser(x=0.5, y=-1.0, theta=0.25, header={"stamp": stamp(1_796_614_484_690_952_831),
                                                          "frame_id": "laser"}),
             kit.laser(x=1.0, theta=-2.5, header={"stamp": stamp(1_796_614_484_890_952_831)})]
    second = [kit.laser(x=1.5, y=0.5, theta=3.0, header={"stamp": stamp(7)})]  # stamps need not increase
    for batch in (first, second):
        assert lab.post("/maps/lab/scans", json={"scans": batch}).status_code == 200
    path = trajectory(lab, "lab")
    assert path["header"]["frame_id"] == "map" and path["version"] == 2
    assert path["unstamped"] == 0 and path["from_version"] == 0
    posted = first + second
    assert [ns_of(p) for p in path["poses"]] == [1_796_614_484_690_952_831, 1_796_614_484_890_952_831, 7]
    for pose, scan in zip(path["poses"], posted, strict=True):
        assert pose["header"]["frame_id"] == "map"
        position, orientation = pose["pose"]["position"], pose["pose"]["orientation"]
        assert (position["x"], position["y"], position["z"]) == (scan["pose"]["x"], scan["pose"]["y"], 0.0)
        assert orientation["x"] == orientation["y"] == 0.0
        assert math.remainder(yaw_of(orientation) - scan["pose"]["theta"], 2 * math.pi) == pytest.approx(0, abs=1e-12)


def test_a_scan_posted_without_a_stamp_gets_the_time_the_service_received_it(lab: TestClient, kit: Any) -> None:
    before = time.time_ns()
    assert lab.post("/maps/lab/scans", json={"scans": [kit.laser(), kit.laser(x=1.0, header={"frame_id": "laser"})]}
                    ).status_code == 200
    after = time.time_ns()
    ranges = np.full(90, 3.0, dtype="<f4").tobytes()  # a binary upload has no header at all
    assert lab.post("/maps/lab/scans", content=ranges, headers={"Content-Type": "application/octet-stream"},
                    params={"x": 0.0, "y": 0.0, "theta": 0.0, "angle_min": -0.7, "angle_increment": 0.015,
                            "range_min": 0.1, "range_max": 20.0}).status_code == 200
    last = time.time_ns()
    stamps = [ns_of(p) for p in trajectory(lab, "lab")["poses"]]
    assert before <= stamps[0] == stamps[1] <= after  # one batch, one time of arrival
    assert after <= stamps[2] <= last


def test_cdr_message_stamps_come_back_with_their_sensor_poses(client: TestClient, kit: Any) -> None:
    ts = get_typestore(Stores.ROS2_JAZZY)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    assert client.post("/maps", json=kit.MAP_3D).status_code == 201
    laser = cdr(ts, laser_msg(ts, wall_ranges(), stamp_ns=1_700_000_000_000_000_123))
    level = {"x": 0.5, "y": -0.5, "z": 0.3, "qx": 0.0, "qy": 0.0, "qz": math.sin(0.4), "qw": math.cos(0.4)}
    assert client.post("/maps/lab/scans", content=laser, params=level,
                       headers={"Content-Type": LASER_CT}).status_code == 200
    cloud = cdr(ts, cloud_msg(ts, kit.cloud_sensor_points(), stamp_ns=1_700_000_000_500_000_000))
    tilted = {"x": 0.25, "y": 0.5, "z": 1.2, **dict(zip(("qx", "qy", "qz", "qw"),
                                                        Rotation.from_euler("zyx", [0.3, 0.2, 0.1]).as_quat()))}
    assert client.post("/maps/hall/scans", content=cloud, params={**tilted, "range_max": 10.0},
                       headers={"Content-Type": CLOUD_CT}).status_code == 200

    (planar,) = trajectory(client, "lab")["poses"]
    assert ns_of(planar) == 1_700_000_000_000_000_123
    assert planar["pose"]["position"] == {"x": 0.5, "y": -0.5, "z": 0.0}  # a 2-D map: on its plane
    assert yaw_of(planar["pose"]["orientation"]) == pytest.approx(0.8, abs=1e-12)
    (swept,) = trajectory(client, "hall")["poses"]
    assert ns_of(swept) == 1_700_000_000_500_000_000
    # a cloud is stored as taken: the sensor's whole pose
    assert swept["pose"]["position"] == {"x": 0.25, "y": 0.5, "z": 1.2}
    assert swept["pose"]["orientation"] == {k: tilted[f"q{k}"] for k in "xyzw"}


def write_bag(path: Path, stamps: list[int]) -> Path:
    """A single-file MCAP bag: the laser fixed in the map (``/tf_static``) and a LaserScan at each stamp."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    t = ts.types
    mount = t["geometry_msgs/msg/TransformStamped"](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="map"),
        child_frame_id="laser", transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=1.5, y=-0.5, z=0.2),
            rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(0.3), w=math.cos(0.3))))
    with Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        scans = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        writer.write(static, stamps[0] - S, ts.serialize_cdr(t["tf2_msgs/msg/TFMessage"](transforms=[mount]),
                                                              "tf2_msgs/msg/TFMessage"))
        for k, ns in enumerate(stamps):
            writer.write(scans, ns + 5_000_000, cdr(ts, laser_msg(ts, wall_ranges(seed=k), stamp_ns=ns)))
    return next(path.glob("*.mcap"))


def test_a_bag_s_message_stamps_come_back_with_their_poses(lab: TestClient, tmp_path: Path) -> None:
    stamps = [1_700_000_100_000_000_000 + k * 100_000_007 for k in range(5)]
    bag = write_bag(tmp_path / "drive", stamps)
    response = lab.post("/maps/lab/bags", content=bag.read_bytes(), headers={"Content-Type": "application/x-mcap"})
    assert response.status_code == 200, response.text
    poses = trajectory(lab, "lab")["poses"]
    assert [ns_of(p) for p in poses] == stamps
    for pose in poses:
        assert pose["pose"]["position"] == {"x": 1.5, "y": -0.5, "z": 0.0}
        assert yaw_of(pose["pose"]["orientation"]) == pytest.approx(0.6, abs=1e-12)


def test_a_restart_gives_the_same_trajectory(make_client: Callable[..., TestClient], kit: Any) -> None:
    first = make_client(snapshot_every=2)  # snapshots on the way and at the stop: they keep the batches they cover
    assert first.post("/maps", json=kit.MAP_2D).status_code == 201
    for k in range(5):
        assert first.post("/maps/lab/scans", json={"scans": [
            kit.laser(x=0.1 * k, header={"stamp": stamp(10 * S + k)}), kit.laser(y=0.2 * k)]}).status_code == 200
    kit.snapshots_stored(first)
    before = trajectory(first, "lab")
    assert len(before["poses"]) == 10 and before["from_version"] == 0
    first.__exit__(None, None, None)

    second = make_client(snapshot_every=2)
    assert trajectory(second, "lab") == before


@pytest.mark.parametrize(("header", "field"), [
    ({"stamp": {"sec": -1, "nanosec": 0}}, "sec"),
    ({"stamp": {"sec": 5, "nanosec": S}}, "nanosec"),
    ({"stamp": {"sec": 5, "nanosec": -1}}, "nanosec"),
    ({"stamp": {"sec": 2**31, "nanosec": 0}}, "sec"),
    ({"stamp": {"sec": 5.5, "nanosec": 0}}, "sec"),
    ({"stamp": {"sec": "5", "nanosec": 0}}, "sec"),
    ({"stamp": {"sec": 5}}, "nanosec"),
    ({"stamp": {"secs": 5, "nsecs": 0}}, "sec"),  # a ROS 1 stamp
])
def test_a_bad_json_stamp_is_refused_naming_it_and_nothing_is_stored(lab: TestClient, kit: Any,
                                                                     header: dict[str, Any], field: str) -> None:
    good = kit.laser(header={"stamp": stamp(S)})
    response = lab.post("/maps/lab/scans", json={"scans": [good, kit.laser(header=header)]})
    assert response.status_code == 422
    assert f"scans.1.laser.header.stamp.{field}" in error_message(response)
    assert kit.version(lab, "lab") == 0 and trajectory(lab, "lab")["poses"] == []


def test_a_bad_message_stamp_is_refused_naming_it_and_nothing_is_stored(lab: TestClient, kit: Any) -> None:
    ts = get_typestore(Stores.ROS2_JAZZY)
    msg = laser_msg(ts, wall_ranges())
    msg.header.stamp.nanosec = 2 * S  # a uint32 CDR can hold, ROS time cannot
    response = lab.post("/maps/lab/scans", content=cdr(ts, msg), headers={"Content-Type": LASER_CT},
                        params={"x": 0.0, "y": 0.0, "z": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0})
    assert response.status_code == 422
    assert "body.header.stamp.nanosec" in error_message(response)
    assert kit.version(lab, "lab") == 0


def test_a_trajectory_longer_than_the_limit_is_refused_naming_it(make_client: Callable[..., TestClient],
                                                                 kit: Any) -> None:
    client = make_client(max_trajectory_poses=3)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()] * 3}).status_code == 200
    assert len(trajectory(client, "lab")["poses"]) == 3
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200
    response = client.get("/maps/lab/trajectory")
    assert response.status_code == 413 and "FUZZYRISK_MAX_TRAJECTORY_POSES" in error_message(response)
    assert client.get("/maps/nowhere/trajectory").status_code == 404


def test_scans_stored_before_stamps_are_reported_unstamped(make_client: Callable[..., TestClient],
                                                          tmp_path: Path) -> None:
    (tmp_path / "data").mkdir()
    shutil.copyfile(DATA_DIR / "stored_log" / DATABASE, tmp_path / "data" / DATABASE)  # written by earlier code
    client = make_client(snapshot_every=10**9)
    path = trajectory(client, "bayes")  # no snapshot: every batch since version 0
    assert path["from_version"] == 0 and len(path["poses"]) > 0
    assert path["unstamped"] == len(path["poses"])
    assert all(ns_of(p) == 0 for p in path["poses"])
