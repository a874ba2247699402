"""Bags in: ``python -m app.import_bag`` and ``POST /maps/{name}/bags``.

Bags are written here with rosbags (ROS 1, rosbag2 with mcap and sqlite3 storage, Humble and Jazzy
message definitions). The expected map is built by posting the same scans as JSON with poses computed
here, independently of the importer: translations interpolated with ``np.interp``, rotations with
scipy's ``Slerp``, the chain map -> odom -> base_link -> sensor composed with scipy's ``Rotation``.
"""

from __future__ import annotations

import io
import math
import os
import re
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import anyio.from_thread
import httpx
import numpy as np
import pytest
import uvicorn
from fastapi.testclient import TestClient
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation, Slerp

from app.ros import bagsize
from app.ros import bags
from app.config import Settings
from app.errors import Unavailable
from app.cli.import_bag import main
from app.api.factory import create_app
from app.schemas import MapCreate
from app.service.mapservice import MapService
from app.maps.writepath import WritePath
from app.storage import SqliteStorage, StorageUnavailable
from tests.app._ros import cloud_msg, grids, laser_msg, wall_ranges
from tests.conftest import error_message

T0 = 10 * 10**9  # the first transform, ns
UPSIDE_DOWN = (Rotation.from_euler("z", 0.1) * Rotation.from_euler("x", math.pi)).as_quat()  # roll pi
TILTED = Rotation.from_euler("zyx", [0.3, 0.4, 0.15]).as_quat()  # a 3-D lidar pitched down, rolled a little
MAP_2D = {"name": "expected", "dimensions": 2, "resolution": 0.1, "origin": [-5.0, -5.0], "size": [10.0, 10.0]}
MAP_3D = {"name": "expected", "dimensions": 3, "resolution": 0.2, "origin": [-4.0, -4.0, -1.0],
          "size": [8.0, 8.0, 4.0]}


@dataclass
class Track:
    """The samples of one dynamic transform."""

    parent: str
    child: str
    stamps: np.ndarray
    positions: np.ndarray
    rotations: Rotation

    def at(self, stamp: int) -> tuple[np.ndarray, Rotation]:
        # independent of fuzzyocc.tf: np.interp for the translation, scipy's Slerp for the rotation
        position = np.array([np.interp(stamp, self.stamps, self.positions[:, i]) for i in range(3)])
        return position, Slerp(self.stamps.astype(np.float64), self.rotations)([float(stamp)])[0]


@dataclass
class Scenario:
    """A robot driving for 10 s: map -> odom at 2 Hz, odom -> base_link at 20 Hz, sensors mounted statically."""

    mounts: dict[str, tuple[list[float], np.ndarray]]  # frame -> (translation, quaternion) on base_link
    scans: list[tuple[str, str, int, Any]] = field(default_factory=list)  # topic, msgtype, stamp, builder(ts)
    tracks: list[Track] = field(default_factory=list)

    @classmethod
    def driving(cls, mounts: dict[str, tuple[list[float], np.ndarray]]) -> Scenario:
        scenario = cls(mounts)
        s = np.arange(0.0, 10.0001, 0.5)
        scenario.tracks.append(Track("map", "odom", (T0 + s * 1e9).astype(np.int64),
                                     np.column_stack([0.05 * s, -0.03 * s, np.zeros_like(s)]),
                                     Rotation.from_euler("z", (0.02 * s)[:, None])))
        s = np.arange(0.0, 10.0001, 0.05)
        scenario.tracks.append(Track("odom", "base_link", (T0 + s * 1e9).astype(np.int64),
                                     np.column_stack([0.12 * s, 0.4 * np.sin(0.3 * s), np.zeros_like(s)]),
                                     Rotation.from_euler("z", (0.25 * s)[:, None])))
        return scenario

    def pose(self, frame: str, stamp: int) -> tuple[np.ndarray, Rotation]:
        """T_map_frame at ``stamp``: the tracks (map first) and the mount, composed here with scipy."""
        mount, quaternion = self.mounts[frame]
        position, rotation = np.asarray(mount, dtype=np.float64), Rotation.from_quat(quaternion)
        for track in reversed(self.tracks):
            p, r = track.at(stamp)
            position, rotation = p + r.apply(position), r * rotation
        return position, rotation


def _stamps() -> list[int]:
    # between TF samples (17 ms past a 50 ms one), plus one before the first and one after the last
    return [T0 - 500_000_000] + [T0 + 13_000_000 + k * 250_000_000 for k in range(39)] + [T0 + 10_500_000_000]


def laser_scenario() -> Scenario:
    scenario = Scenario.driving({"laser": ([0.2, 0.0, 0.3], UPSIDE_DOWN)})
    for k, stamp in enumerate(_stamps()):
        ranges = wall_ranges(n=181, angle_min=-1.5, angle_increment=1 / 60, wall=2.0 + 0.5 * (k % 3), seed=k)
        scenario.scans.append(("/scan", "sensor_msgs/msg/LaserScan", stamp,
                               lambda ts, r=ranges, t=stamp: laser_msg(ts, r, angle_min=-1.5, angle_increment=1 / 60,
                                                                       range_max=8.0, stamp_ns=t)))
    return scenario


def cloud_scenario() -> Scenario:
    """A tilted lidar (organised PointCloud2 with NaNs) and a tilted LaserScan, for a 3-D map."""
    scenario = Scenario.driving({"lidar": ([0.1, 0.0, 1.2], TILTED), "laser": ([0.0, 0.1, 0.8], TILTED)})
    rng = np.random.default_rng(5)
    for k, stamp in enumerate(_stamps()[::3]):
        points = np.column_stack([rng.uniform(1.0, 3.0, 120), rng.uniform(-1.5, 1.5, 120),
                                  rng.uniform(-0.5, 0.5, 120)]).astype(np.float32).astype(np.float64)
        points[rng.choice(120, 10, replace=False)] = np.nan
        scenario.scans.append(("/points", "sensor_msgs/msg/PointCloud2", stamp,
                               lambda ts, p=points, t=stamp: cloud_msg(ts, p, height=4, stamp_ns=t)))
        ranges = wall_ranges(n=61, angle_min=-0.5, angle_increment=1 / 60, wall=2.0, seed=k)
        scenario.scans.append(("/scan", "sensor_msgs/msg/LaserScan", stamp + 1_000_000,
                               lambda ts, r=ranges, t=stamp + 1_000_000: laser_msg(
                                   ts, r, angle_min=-0.5, angle_increment=1 / 60, range_max=3.0, stamp_ns=t)))
    return scenario


# ---------------------------------------------------------------- writing bags


def _transform(ts: Any, parent: str, child: str, stamp: int, position: Any, quaternion: Any) -> Any:
    t = ts.types
    stamp_msg = t["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
    header = (t["std_msgs/msg/Header"](seq=0, stamp=stamp_msg, frame_id=parent)
              if "seq" in t["std_msgs/msg/Header"].__dataclass_fields__
              else t["std_msgs/msg/Header"](stamp=stamp_msg, frame_id=parent))
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = (float(v) for v in quaternion)
    return t["geometry_msgs/msg/TransformStamped"](
        header=header, child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](translation=t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                                                   rotation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))


def _messages(scenario: Scenario, ts: Any) -> list[tuple[str, str, int, Any]]:
    """(topic, type, receive time, message) of the whole bag, in time order."""
    tfm = "tf2_msgs/msg/TFMessage"
    out = [("/tf_static", tfm, T0 - 10**9, ts.types[tfm](transforms=[
        _transform(ts, "base_link", frame, 0, p, q) for frame, (p, q) in scenario.mounts.items()]))]
    for track in scenario.tracks:
        for i, stamp in enumerate(track.stamps):
            out.append(("/tf", tfm, int(stamp), ts.types[tfm](transforms=[
                _transform(ts, track.parent, track.child, int(stamp), track.positions[i],
                           track.rotations[i].as_quat())])))
    for topic, msgtype, stamp, build in scenario.scans:
        out.append((topic, msgtype, stamp + 5_000_000, build(ts)))  # received 5 ms after the stamp
    out.sort(key=lambda m: m[2])
    return out


def _ros1_store() -> Any:
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


def write_bag(scenario: Scenario, path: Path, kind: str, extra: list[tuple[str, str, int, Any]] | None = None) -> Path:
    """Write the scenario as ``kind``: ``ros1``, ``mcap-humble``, ``mcap-jazzy``, ``sqlite3-humble``, ``sqlite3-jazzy``.

    Returns the file to read: the ``.bag``, the ``.mcap`` inside the rosbag2 directory, or the directory.
    """
    if kind == "ros1":
        ts = _ros1_store()
        bag = path.with_suffix(".bag")
        messages = _messages(scenario, ts) + (extra or [])
        with Writer1(bag) as writer:
            connections = {}
            for topic, msgtype, stamp, msg in sorted(messages, key=lambda m: m[2]):
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                writer.write(connections[topic], stamp, ts.serialize_ros1(msg, msgtype))
        return bag
    storage, distro = kind.split("-")
    ts = get_typestore(Stores.ROS2_HUMBLE if distro == "humble" else Stores.ROS2_JAZZY)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    messages = _messages(scenario, ts) + (extra or [])
    with Writer2(path, version=9, storage_plugin=plugin) as writer:
        connections = {}
        for topic, msgtype, stamp, msg in sorted(messages, key=lambda m: m[2]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(connections[topic], stamp, ts.serialize_cdr(msg, msgtype))
    return next(path.glob("*.mcap")) if storage == "mcap" else path


# ---------------------------------------------------------------- the expected map, built by posting JSON


def _ranges_json(ranges: np.ndarray) -> list[Any]:
    return ["nan" if math.isnan(r) else ("inf" if r > 0 else "-inf") if math.isinf(r) else r
            for r in ranges.astype(np.float64).tolist()]


def placed_poses(scenario: Scenario, bag: Path, dims: int, **options: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """The importer's pose of each placed message, checked against the pose computed here with scipy.

    Checked to 1e-12, not bit for bit: two correct computations differ in the last bits, and a
    map is that sensitive (one ulp of pose moved 7 of 10,000 cells by less than 0.001 of risk in
    this scenario). So the expected map is posted with the importer's poses, once they are shown right.
    """
    read = bags.read_bag(bag, bags.BagOptions(**options), dims=dims, limits=bags.DEFAULT_LIMITS)
    placeable = [stamp for _, _, stamp, _ in scenario.scans if T0 <= stamp <= T0 + 10 * 10**9]
    assert [s.stamp_ns for s in read.scans] == placeable
    poses = []
    for s in read.scans:
        position, rotation = scenario.pose(_frame(s), s.stamp_ns)
        assert np.allclose(s.pose.position, position, rtol=0, atol=1e-12)
        assert (Rotation.from_quat(s.pose.orientation).inv() * rotation).magnitude() < 1e-12
        poses.append((np.array(s.pose.position), np.array(s.pose.orientation)))
    return poses


def _frame(scan: Any) -> str:
    return "lidar" if scan.msgtype == "sensor_msgs/msg/PointCloud2" else "laser"


def _heading(quaternion: np.ndarray) -> tuple[float, float]:
    """(theta, turn) by the README's formula: the heading of the sensor's x axis, and its z axis up (1) or down (-1)."""
    qx, qy, qz, qw = quaternion / np.linalg.norm(quaternion)
    theta = math.atan2(2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qy * qy + qz * qz))
    return theta, 1.0 if 1.0 - 2.0 * (qx * qx + qy * qy) > 0.0 else -1.0


def expected_scans(scenario: Scenario, dims: int, poses: list[tuple[np.ndarray, np.ndarray]]) -> list[dict[str, Any]]:
    """The JSON scans the bag's placeable messages are, at ``poses``, converted here by the documented rules."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    first, last = T0, T0 + 10 * 10**9
    out = []
    placeable = [(msgtype, build) for _, msgtype, stamp, build in scenario.scans if first <= stamp <= last]
    assert len(placeable) == len(poses)
    for (msgtype, build), (position, quaternion) in zip(placeable, poses):
        msg = ts.deserialize_cdr(ts.serialize_cdr(build(ts), msgtype), msgtype)  # float32 fields as on the wire
        if msgtype == "sensor_msgs/msg/LaserScan" and dims == 2:
            theta, turn = _heading(quaternion)  # upside down: the sweep turns the other way
            out.append({"pose": {"x": position[0], "y": position[1], "theta": theta},
                        "angle_min": turn * float(msg.angle_min), "angle_increment": turn * float(msg.angle_increment),
                        "ranges": _ranges_json(msg.ranges), "range_min": float(msg.range_min),
                        "range_max": float(msg.range_max)})
            continue
        pose = {"position": position.tolist(), "orientation": quaternion.tolist()}
        if msgtype == "sensor_msgs/msg/LaserScan":  # on a 3-D map: the documented beams-to-points rule
            r = msg.ranges.astype(np.float64)
            keep = r >= float(msg.range_min)
            angles = float(msg.angle_min) + np.flatnonzero(keep) * float(msg.angle_increment)
            dist = np.where(r[keep] >= float(msg.range_max), 2 * float(msg.range_max), r[keep])
            points = np.column_stack([dist * np.cos(angles), dist * np.sin(angles), np.zeros(dist.size)])
            out.append({"pose": pose, "points": points.tolist(), "range_max": float(msg.range_max)})
        else:
            layout = np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3, "offsets": [0, 4, 8],
                               "itemsize": msg.point_step})
            rec = np.frombuffer(bytes(msg.data), dtype=layout)
            points = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
            points = points[np.isfinite(points).all(axis=1)]
            out.append({"pose": pose, "points": points.tolist(), "range_max": 100.0})
    return out


def expected_map(client: TestClient, scenario: Scenario, spec: dict[str, Any], bag: Path,
                 **options: Any) -> tuple[np.ndarray, np.ndarray]:
    assert client.post("/maps", json=spec).status_code == 201
    scans = expected_scans(scenario, spec["dimensions"], placed_poses(scenario, bag, spec["dimensions"], **options))
    for i in range(0, len(scans), 16):
        response = client.post(f"/maps/{spec['name']}/scans", json={"scans": scans[i:i + 16]})
        assert response.status_code == 200, response.text
    return grids(client, spec["name"])


def assert_same(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> None:
    assert b[1].any(), "nothing observed: the comparison would prove nothing"
    assert np.array_equal(a[1], b[1])
    assert np.array_equal(a[0].view(np.uint32), b[0].view(np.uint32))  # bit for bit


# ---------------------------------------------------------------- through the service: an upload


BAG_CT = {".bag": "application/x-rosbag", ".mcap": "application/x-mcap"}


def upload(client: TestClient, name: str, path: Path, content_type: str | None = None, **params: Any) -> Any:
    return client.post(f"/maps/{name}/bags", content=path.read_bytes(), params=params,
                       headers={"Content-Type": content_type or BAG_CT[path.suffix]})


@pytest.mark.parametrize(("kind", "content_type"), [("ros1", None), ("mcap-humble", None),
                                                     ("mcap-humble", "application/mcap"),
                                                     ("mcap-jazzy", "application/octet-stream")])
def test_an_uploaded_bag_equals_the_scans_posted_with_interpolated_poses(client: TestClient, tmp_path: Path,
                                                                         kind: str, content_type: str | None) -> None:
    scenario = laser_scenario()
    bag = write_bag(scenario, tmp_path / "drive", kind)
    assert client.post("/maps", json={**MAP_2D, "name": "bag"}).status_code == 201
    # as its own type (MCAP: application/mcap, what the service's downloads are, or application/x-mcap), or as
    # application/octet-stream (what generated clients send): told by its first bytes
    response = upload(client, "bag", bag, content_type)
    assert response.status_code == 200, response.text
    summary = response.json()
    assert summary["complete"] is True and summary["stopped"] is None
    assert summary["messages"] == 41 and summary["scans_fused"] == 39
    assert summary["skipped"] == {"before the first transform map -> odom": 1,
                                  "after the last transform map -> odom": 1}
    assert summary["topics"] == {"/scan": "sensor_msgs/msg/LaserScan"}
    assert_same(grids(client, "bag"), expected_map(client, scenario, MAP_2D, bag))


def test_an_uploaded_3d_bag_places_a_tilted_lidar_and_laser(client: TestClient, tmp_path: Path) -> None:
    scenario = cloud_scenario()
    bag = write_bag(scenario, tmp_path / "drive3d", "mcap-jazzy")
    assert client.post("/maps", json={**MAP_3D, "name": "bag"}).status_code == 201
    response = upload(client, "bag", bag)
    assert response.status_code == 200, response.text
    assert response.json()["scans_fused"] == 26  # 14 stamps x 2 topics, less the first and the last
    assert_same(grids(client, "bag"), expected_map(client, scenario, MAP_3D, bag))


def test_a_pose_topic_places_its_frame_instead_of_tf(client: TestClient, tmp_path: Path) -> None:
    scenario = laser_scenario()
    ts = get_typestore(Stores.ROS2_JAZZY)
    # odometry in the map frame, at 10 Hz; /tf keeps map -> odom -> base_link, which must not be used
    odometry = Track("map", "base_link", (T0 + np.arange(0, 101) * 10**8).astype(np.int64),
                     np.column_stack([np.linspace(-1, 1, 101), np.linspace(0.5, -0.5, 101), np.zeros(101)]),
                     Rotation.from_euler("z", np.linspace(0.0, 2.0, 101)[:, None]))
    t = ts.types
    extra = []
    for i, stamp in enumerate(odometry.stamps):
        x, y, z = odometry.positions[i]
        qx, qy, qz, qw = odometry.rotations[i].as_quat()
        extra.append(("/odom", "nav_msgs/msg/Odometry", int(stamp), t["nav_msgs/msg/Odometry"](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=int(stamp) // 10**9,
                                                                                 nanosec=int(stamp) % 10**9),
                                            frame_id="map"),
            child_frame_id="base_link",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                                 orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)),
                covariance=np.zeros(36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                   angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36)))))
    bag = write_bag(scenario, tmp_path / "odom", "mcap-jazzy", extra)
    assert client.post("/maps", json={**MAP_2D, "name": "bag"}).status_code == 201
    response = upload(client, "bag", bag, pose_topic="/odom")
    assert response.status_code == 200, response.text
    assert response.json()["skipped"] == {"before the first transform map -> base_link": 1,
                                          "after the last transform map -> base_link": 1}
    by_odometry = Scenario(scenario.mounts, scenario.scans, [odometry])
    assert_same(grids(client, "bag"), expected_map(client, by_odometry, MAP_2D, bag, pose_topic="/odom"))


def test_upload_refusals_are_4xx_and_change_nothing(make_client: Any, tmp_path: Path) -> None:
    limit = 2 * 2**20
    client = make_client(max_body_bytes=limit)
    scenario = laser_scenario()
    bag = write_bag(scenario, tmp_path / "drive", "mcap-jazzy")
    ros1 = write_bag(scenario, tmp_path / "drive1", "ros1")
    assert client.post("/maps", json={**MAP_2D, "name": "bag"}).status_code == 201
    data = bag.read_bytes()

    def refused(status: int, content: bytes, content_type: str, **params: Any) -> str:
        response = client.post("/maps/bag/bags", content=content, params=params,
                               headers={"Content-Type": content_type})
        assert response.status_code == status, response.text
        assert client.get("/maps/bag").json()["version"] == 0
        return error_message(response)

    assert "application/mcap" in refused(415, data, "text/plain")
    assert "neither" in refused(422, b"PK\x03\x04" + data, "application/octet-stream")
    assert "not a .bag file" in refused(422, data, "application/x-rosbag")  # an mcap labelled as ROS 1
    assert "not a readable bag" in refused(422, data[:len(data) // 2], "application/x-mcap")
    assert "/nowhere" in refused(422, data, "application/x-mcap", topic="/nowhere")
    assert "--pose-topic" in refused(422, data, "application/x-mcap", pose_topic="/odom")
    assert "not a readable bag" in refused(422, ros1.read_bytes()[:4096], "application/x-rosbag")
    assert "FUZZYRISK_MAX_BODY_BYTES" in refused(413, data + bytes(limit), "application/x-mcap")
    # damaged files, whatever rosbags makes of them (KeyError, AssertionError, MemoryError...), are 422s
    rng = np.random.default_rng(4)
    for _ in range(20):
        damaged = bytearray(data)
        at = rng.integers(16, len(damaged), size=4)
        damaged[at[0]:at[0] + 8] = rng.integers(0, 256, size=len(damaged[at[0]:at[0] + 8]), dtype=np.uint8).tobytes()
        del damaged[at[1]:at[1] + 32]
        response = client.post("/maps/bag/bags", content=bytes(damaged), headers={"Content-Type": "application/x-mcap"})
        assert response.status_code in (200, 422), response.text
    assert client.post("/maps/bag/bags", content=b"").status_code == 415
    # a bag whose frames never reach the map frame: nothing fused, every message counted
    response = client.post("/maps/bag/bags", content=data, params={"map_frame": "world"},
                           headers={"Content-Type": "application/x-mcap"})
    assert response.status_code == 200
    assert response.json()["scans_fused"] == 0
    assert response.json()["skipped"] == {"no chain of transforms from laser to world": 41}


def test_messages_a_map_cannot_take_are_skipped_with_the_reason(client: TestClient, tmp_path: Path) -> None:
    # a tilted lidar and a tilted laser on a 2-D map: the cloud is projected, the laser refused and counted
    bag = write_bag(cloud_scenario(), tmp_path / "drive3d", "mcap-humble")
    assert client.post("/maps", json={**MAP_2D, "name": "flat"}).status_code == 201
    response = upload(client, "flat", bag)
    assert response.status_code == 200, response.text
    summary = response.json()
    assert summary["scans_fused"] == 13
    (reason, count), = [(k, v) for k, v in summary["skipped"].items() if k.startswith("refused")]
    assert count == 13 and "tilted" in reason and "3-D map" in reason


# ---------------------------------------------------------------- an upload is admitted once, and never half-answered


BATCH = 8  # scans per batch in these tests: the laser scenario's 39 placed scans take 5 batches


def test_an_admitted_import_is_not_refused_part_way_for_the_line(
        make_client: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Other clients fill the map's line once the import's first batch is in: its later batches still go in.
    With room for one batch in line, the import's own body, batches or reading never count against it."""
    client = make_client(max_scans_per_batch=BATCH, max_pending_batches=1)
    bag = write_bag(laser_scenario(), tmp_path / "drive", "mcap-jazzy")
    assert client.post("/maps", json={**MAP_2D, "name": "bag"}).status_code == 201
    line_full = False
    add, admit = WritePath.add_parsed_scans, WritePath._admit

    async def add_then_fill(self: WritePath, *args: Any, **kwargs: Any) -> Any:
        nonlocal line_full
        result = await add(self, *args, **kwargs)
        line_full = True  # from now on, every new batch of this map would be refused
        return result

    def full(self: WritePath, entry: Any) -> None:
        if line_full:
            raise Unavailable("the line is full", headers={"Retry-After": "1"})
        admit(self, entry)

    monkeypatch.setattr(WritePath, "add_parsed_scans", add_then_fill)
    monkeypatch.setattr(WritePath, "_admit", full)
    response = upload(client, "bag", bag)
    assert response.status_code == 200, response.text
    summary = response.json()
    assert summary["complete"] is True and summary["batches"] == 5 and summary["scans_fused"] == 39
    assert summary["version"] == 5 == client.get("/maps/bag").json()["version"]
    # a new import is admitted (or not) as a whole: refused before anything is applied
    refused = upload(client, "bag", bag)
    assert refused.status_code == 503 and refused.headers["retry-after"] == "1"
    assert client.get("/maps/bag").json()["version"] == 5


@pytest.mark.parametrize("failing_commit", [1, 3])
def test_a_failure_part_way_answers_200_with_what_was_applied(
        make_client: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing_commit: int) -> None:
    """A full disk at the third batch: 200, the two batches before it applied, the error in ``stopped``
    (a retryable 503 would have the client send the bag again, and fuse its first part twice). At the
    first batch: the storage answer (503 STORAGE_UNAVAILABLE, Retry-After), nothing applied."""
    client = make_client(max_scans_per_batch=BATCH)
    bag = write_bag(laser_scenario(), tmp_path / "drive", "mcap-jazzy")
    assert client.post("/maps", json={**MAP_2D, "name": "bag"}).status_code == 201
    commits = 0
    append = SqliteStorage.append_batches

    def fill_disk(self: SqliteStorage, records: Any) -> list[int]:
        nonlocal commits
        commits += 1
        if commits >= failing_commit:
            raise StorageUnavailable("database or disk is full")
        return append(self, records)

    monkeypatch.setattr(SqliteStorage, "append_batches", fill_disk)
    response = upload(client, "bag", bag)
    if failing_commit == 1:
        assert response.status_code == 503 and response.json()["code"] == "STORAGE_UNAVAILABLE"
        assert int(response.headers["retry-after"]) > 0
        assert client.get("/maps/bag").json()["version"] == 0
        return
    assert response.status_code == 200, response.text
    assert "retry-after" not in response.headers
    summary = response.json()
    assert summary["complete"] is False
    assert summary["batches"] == 2 and summary["scans_fused"] == 2 * BATCH and summary["version"] == 2
    assert summary["stopped"]["code"] == "STORAGE_UNAVAILABLE"
    assert "after 2 batches" in summary["stopped"]["message"] and set(summary["stopped"]) == {
        "code", "message", "details"}
    assert client.get("/maps/bag").json()["version"] == 2
    assert client.get("/maps/bag").json()["scans_fused"] == 2 * BATCH


def test_scans_read_for_a_map_deleted_and_created_again_are_refused_409(
        client: TestClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The bag is read for the 2-D map; meanwhile the name becomes a 3-D map: 409, nothing stored."""
    bag = write_bag(laser_scenario(), tmp_path / "drive", "mcap-jazzy")
    assert client.post("/maps", json={**MAP_2D, "name": "bag"}).status_code == 201
    service: MapService = client.app.state.service  # type: ignore[attr-defined]
    declared = bagsize.decompressed_bytes

    def and_replace_the_map(path: Path) -> int:
        # in the upload's reading thread: the map is replaced on the event loop meanwhile
        anyio.from_thread.run(service.maps.delete_map, "bag")
        anyio.from_thread.run(service.maps.create_map, MapCreate(**{**MAP_3D, "name": "bag"}))
        return declared(path)

    monkeypatch.setattr(bagsize, "decompressed_bytes", and_replace_the_map)
    response = upload(client, "bag", bag)
    assert response.status_code == 409, response.text
    assert "created again" in error_message(response)
    info = client.get("/maps/bag").json()
    assert info["dimensions"] == 3 and info["version"] == 0
    stored = service.storage.load_map("bag")
    assert stored is not None and stored.batches == []


def test_an_upload_is_fused_batch_by_batch_as_it_is_read(
        make_client: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The first batch is fused before the last message is read: the bag is never held whole in memory."""
    client = make_client(max_scans_per_batch=BATCH)
    bag = write_bag(laser_scenario(), tmp_path / "drive", "mcap-jazzy")
    assert client.post("/maps", json={**MAP_2D, "name": "bag"}).status_code == 201
    events: list[str] = []
    place, add = bags._place, WritePath.add_parsed_scans

    def placing(*args: Any, **kwargs: Any) -> Any:
        events.append("read")
        return place(*args, **kwargs)

    async def fusing(self: WritePath, *args: Any, **kwargs: Any) -> Any:
        events.append("fuse")
        return await add(self, *args, **kwargs)

    monkeypatch.setattr(bags, "_place", placing)
    monkeypatch.setattr(WritePath, "add_parsed_scans", fusing)
    assert upload(client, "bag", bag).json()["batches"] == 5
    assert events.index("fuse") < len(events) - 1 - events[::-1].index("read")
    assert events[:BATCH + 2] == ["read"] * (BATCH + 1) + ["fuse"]  # the unplaceable first message, then 8


def test_an_upload_is_written_to_the_data_directory_and_a_full_disk_is_the_storage_answer(
        make_client: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    client = make_client()
    temp_dir = tmp_path / "data" / "tmp"  # <data dir>/tmp (Settings.temp_dir), not the system's /tmp
    bag = write_bag(laser_scenario(), tmp_path / "drive", "mcap-jazzy")
    assert client.post("/maps", json={**MAP_2D, "name": "bag"}).status_code == 201
    directories: list[Path] = []
    mkstemp = tempfile.mkstemp

    def full(*args: Any, **kwargs: Any) -> tuple[int, str]:
        directories.append(Path(kwargs["dir"]) if kwargs.get("dir") else Path(tempfile.gettempdir()))
        _, name = mkstemp(*args, **kwargs)
        return os.open("/dev/full", os.O_WRONLY), name  # every write: ENOSPC, as on a full disk

    monkeypatch.setattr(tempfile, "mkstemp", full)
    response = upload(client, "bag", bag)
    assert response.status_code == 503, response.text
    assert response.json()["code"] == "STORAGE_UNAVAILABLE" and int(response.headers["retry-after"]) > 0
    assert directories == [temp_dir]
    monkeypatch.undo()
    assert upload(client, "bag", bag).status_code == 200
    assert client.get("/maps/bag").json()["version"] == 1
    assert list(temp_dir.glob("*")) == []  # each upload's file removed, the failed one too


def test_the_files_a_killed_run_left_are_removed_at_start(make_client: Any, tmp_path: Path) -> None:
    left = tmp_path / "data" / "tmp" / "fuzzyrisk-bag-killed.mcap"
    left.parent.mkdir(parents=True)
    left.write_bytes(b"\x89MCAP0\r\n")
    make_client(data_dir=tmp_path / "data")
    assert not left.exists()


# ---------------------------------------------------------------- a map in its own frame


def robot1_scenario() -> Scenario:
    """The laser scenario in a fleet's namespace: its TF tree ends in robot1/map, not map."""
    scenario = laser_scenario()
    scenario.tracks[0].parent = "robot1/map"
    return scenario


def test_an_upload_places_the_scans_in_the_maps_own_frame(client: TestClient, tmp_path: Path) -> None:
    bag = write_bag(robot1_scenario(), tmp_path / "robot1", "mcap-jazzy")
    assert client.post("/maps", json={**MAP_2D, "name": "bag", "frame_id": "robot1/map"}).status_code == 201
    response = upload(client, "bag", bag)
    assert response.status_code == 200, response.text
    assert response.json()["scans_fused"] == 39
    assert response.json()["skipped"] == {"before the first transform robot1/map -> odom": 1,
                                          "after the last transform robot1/map -> odom": 1}
    # map_frame still names another frame when the bag's tree has no robot1/map
    other = write_bag(laser_scenario(), tmp_path / "plain", "mcap-jazzy")
    assert upload(client, "bag", other, map_frame="map").json()["scans_fused"] == 39


# ---------------------------------------------------------------- the command


@pytest.fixture
def live_service(tmp_path: Path) -> Iterator[str]:
    """The service's URL: uvicorn on a free port of 127.0.0.1, in a thread of this process (stopped at the end)."""
    settings = Settings(data_dir=tmp_path / "served", plan_warmup=False, plan_workers=1)
    app = create_app(settings)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    assert server.started
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60) as http:
            while http.get("/ready").json()["status"] == "starting" and time.monotonic() < deadline:
                time.sleep(0.05)
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)


def _servedgrids(url: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    out = []
    for layer in ("risk", "observed"):
        response = httpx.get(f"{url}/maps/{name}/risk", params={"format": "npy", "layer": layer}, timeout=60)
        assert response.status_code == 200, response.text
        out.append(np.load(io.BytesIO(response.content), allow_pickle=False))
    return out[0], out[1]


@pytest.mark.parametrize("kind", ["sqlite3-humble", "ros1"])
def test_the_command_in_process_and_through_the_service_gives_the_posted_map(
        client: TestClient, live_service: str, tmp_path: Path, kind: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    url = live_service
    scenario = laser_scenario()
    bag = write_bag(scenario, tmp_path / "drive", kind)
    expected = expected_map(client, scenario, MAP_2D, bag)
    box = ["--origin", "-5", "-5", "--size", "10", "10", "--resolution", "0.1"]

    local = tmp_path / "local.npy"
    assert main([str(bag), *box, "--npy", str(local)]) == 0
    out, err = capsys.readouterr()
    assert "41 scan messages read, 39 fused, 2 skipped (1 before the first transform map -> odom, " \
           "1 after the last transform map -> odom)" in out
    assert "scans/s" in out  # stderr is no terminal: plain progress lines, the last with the whole pass
    assert re.search(r"^fuzzyrisk-import-bag: fusing: 41/41 messages, 39 scans fused; [\d.,]+ messages/s, "
                     r"\d\d:\d\d elapsed, 00:00 left$", err, re.MULTILINE), err
    assert np.array_equal(np.load(local).view(np.uint32), expected[0].view(np.uint32))

    for body in ("cdr", "json"):
        assert main([str(bag), *box, "--url", url, "--map", f"bag_{body}", "--body", body]) == 0, capsys.readouterr()
        assert "39 fused" in capsys.readouterr().out
        assert_same(_servedgrids(url, f"bag_{body}"), expected)


def test_the_command_creates_the_map_in_its_map_frame_and_appends_in_the_maps_own(
        live_service: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url = live_service
    bag = write_bag(robot1_scenario(), tmp_path / "robot1", "mcap-jazzy")
    box = ["--origin", "-5", "-5", "--size", "10", "10", "--resolution", "0.1"]
    assert main([str(bag), *box, "--map-frame", "robot1/map", "--url", url, "--map", "r1"]) == 0
    assert "39 fused" in capsys.readouterr().out
    info = httpx.get(f"{url}/maps/r1", timeout=60).json()
    assert info["frame_id"] == "robot1/map" and info["scans_fused"] == 39
    # --append without --map-frame: the scans are placed in the map's own frame
    assert main([str(bag), "--url", url, "--map", "r1", "--append", "--body", "json"]) == 0
    assert "39 fused" in capsys.readouterr().out
    assert httpx.get(f"{url}/maps/r1", timeout=60).json()["scans_fused"] == 78


def test_the_command_reads_a_3d_bag_into_a_3d_map(client: TestClient, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    scenario = cloud_scenario()
    bag = write_bag(scenario, tmp_path / "drive3d", "sqlite3-jazzy")
    expected = expected_map(client, scenario, MAP_3D, bag)
    local = tmp_path / "local.npy"
    assert main([str(bag), "--origin", "-4", "-4", "-1", "--size", "8", "8", "4", "--resolution", "0.2",
                 "--npy", str(local)]) == 0
    assert "26 fused" in capsys.readouterr().out
    assert np.array_equal(np.load(local).view(np.uint32), expected[0].view(np.uint32))


def test_the_command_shows_its_two_passes_in_order(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_bag(laser_scenario(), tmp_path / "drive", "mcap-jazzy")
    assert main([str(bag)]) == 0  # no --origin: a first pass sizes the map
    lines = [line.split(";")[0] for line in capsys.readouterr().err.splitlines()]
    assert lines[0] == "fuzzyrisk-import-bag: reading to size the map: 41/41 messages"
    assert lines[1].startswith("fuzzyrisk-import-bag: drive.mcap: 41 scan messages on /scan, ")
    assert lines[-1] == "fuzzyrisk-import-bag: fusing: 41/41 messages, 39 scans fused"


def test_the_command_fails_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path / "missing.bag")]) == 1
    assert "no such file" in capsys.readouterr().err
    bag = write_bag(laser_scenario(), tmp_path / "drive", "mcap-jazzy")
    assert main([str(bag), "--topic", "/nowhere"]) == 1
    assert "no topic '/nowhere'" in capsys.readouterr().err
    assert main([str(bag), "--map-frame", "world"]) == 1
    assert "no scan could be placed" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(bag), "--origin", "0", "0"])  # without --size
