"""POST /maps/{name}/scans with CDR-serialized sensor_msgs LaserScan and PointCloud2 bodies.

Each accepted body must give the map, bit for bit, that posting the same scan as JSON (or binary) gives;
the expected poses and points are computed here, independently of app.ros.messages_in.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from app.ros import messages_in
from app.scans import Limits
from tests.app._ros import (
    CLOUD_CT,
    LASER_CT,
    STORES,
    cdr,
    cloud_msg,
    grids,
    laser_msg,
    store,
    wall_ranges,
)
from tests.conftest import error_message

STORE_NAMES = list(STORES)


def _assert_same_map(client: TestClient, a: str, b: str) -> None:
    risk_a, observed_a = grids(client, a)
    risk_b, observed_b = grids(client, b)
    assert observed_a.any(), "the scan observed nothing: the comparison would prove nothing"
    assert np.array_equal(observed_a, observed_b)
    assert np.array_equal(risk_a.view(np.uint32), risk_b.view(np.uint32))  # bit for bit


def _pose_query(position: Any, quaternion: Any) -> dict[str, float]:
    return dict(zip(("x", "y", "z", "qx", "qy", "qz", "qw"), [float(v) for v in (*position, *quaternion)]))


def _post_cdr(client: TestClient, name: str, body: bytes, content_type: str, params: dict[str, Any]) -> Any:
    return client.post(f"/maps/{name}/scans", content=body, params=params, headers={"Content-Type": content_type})


def _json_laser(ranges: np.ndarray, *, x: float, y: float, theta: float, angle_min: float, angle_increment: float,
                range_min: float, range_max: float) -> dict[str, Any]:
    tokens = ["nan" if math.isnan(r) else ("inf" if r > 0 else "-inf") if math.isinf(r) else r
              for r in ranges.astype(np.float64).tolist()]
    return {"pose": {"x": x, "y": y, "theta": theta}, "angle_min": angle_min, "angle_increment": angle_increment,
            "ranges": tokens, "range_min": range_min, "range_max": range_max}


def _heading(quaternion: Any) -> float:
    """The heading of the sensor's x axis by the README's formula (the documented contract, so bit for bit)."""
    qx, qy, qz, qw = np.asarray(quaternion, dtype=np.float64) / np.linalg.norm(quaternion)
    theta = math.atan2(2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qy * qy + qz * qz))
    # and it is the heading scipy finds (to rounding)
    matrix = Rotation.from_quat(quaternion).as_matrix()
    assert abs(theta - math.atan2(matrix[1, 0], matrix[0, 0])) < 1e-12
    return theta


def _f32(value: float) -> float:
    return float(np.float32(value))  # what a float32 message field holds


# ---------------------------------------------------------------- LaserScan


@pytest.mark.parametrize("store_name", STORE_NAMES)
def test_laserscan_body_equals_the_json_scan_on_a_2d_map(client: TestClient, kit: Any, store_name: str) -> None:
    ts = store(store_name)
    ranges = wall_ranges()
    body = cdr(ts, laser_msg(ts, ranges))
    quaternion = Rotation.from_euler("z", 0.7).as_quat()
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps", json={**kit.MAP_2D, "name": "lab_json"})
    response = _post_cdr(client, "lab", body, LASER_CT, _pose_query([0.3, -0.2, 0.25], quaternion))
    assert response.status_code == 200, response.text
    scan = _json_laser(ranges, x=0.3, y=-0.2, theta=_heading(quaternion), angle_min=_f32(-1.2),
                       angle_increment=_f32(0.02), range_min=_f32(0.1), range_max=8.0)
    assert client.post("/maps/lab_json/scans", json={"scans": [scan]}).status_code == 200
    _assert_same_map(client, "lab", "lab_json")
    # every special value counted as JSON counts it: rays are hits and no-returns (+inf, >= range_max)
    assert response.json()["rays"] == int(np.count_nonzero(ranges >= np.float32(0.1)))


def test_big_endian_cdr_reads_as_little_endian(client: TestClient, kit: Any) -> None:
    ts = store("jazzy")
    msg = laser_msg(ts, wall_ranges())
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps", json={**kit.MAP_2D, "name": "lab_be"})
    pose = _pose_query([0, 0, 0], [0, 0, 0, 1])
    assert _post_cdr(client, "lab", cdr(ts, msg), LASER_CT, pose).status_code == 200
    assert _post_cdr(client, "lab_be", cdr(ts, msg, little_endian=False), LASER_CT, pose).status_code == 200
    _assert_same_map(client, "lab", "lab_be")


def test_a_laser_mounted_upside_down_sweeps_the_other_way(client: TestClient, kit: Any) -> None:
    ts = store("humble")
    ranges = wall_ranges(seed=5)
    # asymmetric scene: only the left half of the sweep sees the wall
    ranges[60:] = np.inf
    body = cdr(ts, laser_msg(ts, ranges))
    yaw = 0.4
    upside_down = (Rotation.from_euler("z", yaw) * Rotation.from_euler("x", math.pi)).as_quat()
    for name in ("lab", "lab_json", "lab_naive"):
        client.post("/maps", json={**kit.MAP_2D, "name": name})
    assert _post_cdr(client, "lab", body, LASER_CT, _pose_query([1, 1, 0.3], upside_down)).status_code == 200
    # the sensor's +y points to the map's -y side: beam angles count clockwise in the map
    flipped = _json_laser(ranges, x=1.0, y=1.0, theta=_heading(upside_down), angle_min=-_f32(-1.2),
                          angle_increment=-_f32(0.02), range_min=_f32(0.1), range_max=8.0)
    naive = {**flipped, "angle_min": _f32(-1.2), "angle_increment": _f32(0.02)}
    assert client.post("/maps/lab_json/scans", json={"scans": [flipped]}).status_code == 200
    assert client.post("/maps/lab_naive/scans", json={"scans": [naive]}).status_code == 200
    _assert_same_map(client, "lab", "lab_json")
    assert not np.array_equal(grids(client, "lab")[0], grids(client, "lab_naive")[0])


def test_a_tilted_laser_is_refused_on_a_2d_map_and_changes_nothing(client: TestClient, kit: Any) -> None:
    ts = store("jazzy")
    client.post("/maps", json=kit.MAP_2D)
    tilted = Rotation.from_euler("y", 0.3).as_quat()
    response = _post_cdr(client, "lab", cdr(ts, laser_msg(ts, wall_ranges())), LASER_CT, _pose_query([0, 0, 0], tilted))
    assert response.status_code == 422
    assert "tilted" in error_message(response) and "3-D map" in error_message(response)
    assert kit.version(client, "lab") == 0


@pytest.mark.parametrize("store_name", STORE_NAMES)
def test_a_tilted_laser_on_a_3d_map_equals_the_json_cloud_of_its_beams(client: TestClient, kit: Any,
                                                                     store_name: str) -> None:
    ts = store(store_name)
    ranges = wall_ranges(wall=2.0, seed=11)
    body = cdr(ts, laser_msg(ts, ranges, angle_min=-1.2, angle_increment=0.02, range_min=0.1, range_max=3.5))
    position, quaternion = [0.2, 0.1, 1.2], Rotation.from_euler("zyx", [0.5, 0.35, -0.2]).as_quat()
    client.post("/maps", json=kit.MAP_3D)
    client.post("/maps", json={**kit.MAP_3D, "name": "hall_json"})
    response = _post_cdr(client, "hall", body, LASER_CT, _pose_query(position, quaternion))
    assert response.status_code == 200, response.text
    # the documented rule: beam i at angle_min + i * angle_increment, a no-return at 2 * range_max
    r = ranges.astype(np.float64)
    keep = r >= _f32(0.1)
    angles = _f32(-1.2) + np.flatnonzero(keep) * _f32(0.02)
    dist = np.where(r[keep] >= 3.5, 7.0, r[keep])
    points = np.column_stack([dist * np.cos(angles), dist * np.sin(angles), np.zeros(dist.size)])
    cloud = {"pose": {"position": position, "orientation": quaternion.tolist()}, "points": points.tolist(),
             "range_max": 3.5}
    assert client.post("/maps/hall_json/scans", json={"scans": [cloud]}).status_code == 200
    _assert_same_map(client, "hall", "hall_json")
    # the tilt is real: the beams reach cells above and below the sensor's height
    observed = grids(client, "hall")[1]
    assert len(np.unique(np.nonzero(observed)[2])) > 3


# ---------------------------------------------------------------- PointCloud2


def _cloud_points(n: int = 300, seed: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(1.5, 3.0, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-0.8, 0.8, n)])


def _post_json_cloud(client: TestClient, name: str, points: np.ndarray, position: Any, quaternion: Any,
                     range_max: float) -> Any:
    cloud = {"pose": {"position": list(position), "orientation": list(quaternion)}, "points": points.tolist(),
             "range_max": range_max}
    return client.post(f"/maps/{name}/scans", json={"scans": [cloud]})


@pytest.mark.parametrize("store_name", STORE_NAMES)
def test_pointcloud2_with_intensity_gives_exactly_its_points(client: TestClient, kit: Any, store_name: str) -> None:
    ts = store(store_name)
    points = _cloud_points().astype(np.float32).astype(np.float64)
    msg = cloud_msg(ts, points)  # x, y, z, intensity: point_step 16
    assert msg.point_step == 16
    position, quaternion = [0.0, 0.5, 1.0], Rotation.from_euler("z", -0.3).as_quat().tolist()
    for name in ("hall", "hall_json", "hall_raw"):
        client.post("/maps", json={**kit.MAP_3D, "name": name})
    params = {**_pose_query(position, quaternion), "range_max": 6.0}
    response = _post_cdr(client, "hall", cdr(ts, msg), CLOUD_CT, params)
    assert response.status_code == 200, response.text
    assert response.json()["rays"] == 300
    assert _post_json_cloud(client, "hall_json", points, position, quaternion, 6.0).status_code == 200
    _assert_same_map(client, "hall", "hall_json")
    # the same bytes posted raw: refused without their layout (they were read as 400 garbage points) ...
    raw = bytes(msg.data)
    raw_params = {"x": 0.0, "y": 0.5, "z": 1.0, "qx": quaternion[0], "qy": quaternion[1], "qz": quaternion[2],
                  "qw": quaternion[3], "range_max": 6.0}
    refused = client.post("/maps/hall_raw/scans", content=raw, params=raw_params,
                          headers={"Content-Type": "application/octet-stream"})
    assert refused.status_code == 422
    assert "point_step" in error_message(refused)
    assert kit.version(client, "hall_raw") == 0
    # ... and read right with it
    accepted = client.post("/maps/hall_raw/scans", content=raw, params={**raw_params, "point_step": 16},
                           headers={"Content-Type": "application/octet-stream"})
    assert accepted.status_code == 200, accepted.text
    assert accepted.json()["rays"] == 300
    _assert_same_map(client, "hall", "hall_raw")


@pytest.mark.parametrize(("dtype", "bigendian"), [("f4", True), ("f8", False), ("f8", True)])
def test_pointcloud2_datatypes_and_byte_orders(client: TestClient, kit: Any, dtype: str, bigendian: bool) -> None:
    ts = store("jazzy")
    points = _cloud_points(seed=4)
    if dtype == "f4":
        points = points.astype(np.float32).astype(np.float64)
    msg = cloud_msg(ts, points, dtype=dtype, bigendian=bigendian, extra=("intensity", "ring"))
    position, quaternion = [0.1, 0.0, 1.3], [0.0, 0.0, 0.0, 1.0]
    client.post("/maps", json=kit.MAP_3D)
    client.post("/maps", json={**kit.MAP_3D, "name": "hall_json"})
    response = _post_cdr(client, "hall", cdr(ts, msg), CLOUD_CT, {**_pose_query(position, quaternion),
                                                                   "range_max": 6.0})
    assert response.status_code == 200, response.text
    assert _post_json_cloud(client, "hall_json", points, position, quaternion, 6.0).status_code == 200
    _assert_same_map(client, "hall", "hall_json")


def test_organised_cloud_drops_its_nan_points_and_honours_row_step(client: TestClient, kit: Any) -> None:
    ts = store("humble")
    points = _cloud_points(n=300, seed=9).astype(np.float32).astype(np.float64)
    holes = np.random.default_rng(1).choice(300, size=40, replace=False)
    points[holes] = np.nan  # no return: an organised driver keeps the slot
    msg = cloud_msg(ts, points, height=10, row_pad=8, dense=False)
    assert (msg.height, msg.width, msg.row_step) == (10, 30, 30 * 16 + 8)
    position, quaternion = [0.0, 0.0, 1.0], Rotation.from_euler("x", 0.2).as_quat().tolist()
    client.post("/maps", json=kit.MAP_3D)
    client.post("/maps", json={**kit.MAP_3D, "name": "hall_json"})
    response = _post_cdr(client, "hall", cdr(ts, msg), CLOUD_CT, {**_pose_query(position, quaternion),
                                                                   "range_max": 6.0})
    assert response.status_code == 200, response.text
    assert response.json()["rays"] == 260
    finite = points[np.isfinite(points).all(axis=1)]
    assert _post_json_cloud(client, "hall_json", finite, position, quaternion, 6.0).status_code == 200
    _assert_same_map(client, "hall", "hall_json")


@pytest.mark.parametrize(("offsets", "point_step", "row_pad"), [
    ((3, 7, 11), 21, 5),  # a driver's float32 x y z at an odd offset and an odd point_step, rows padded
    ((0, 4, 8), 48, 0),  # an Ouster driver's point: 48 bytes, x y z first
    ((8, 4, 0), 16, 8),  # z y x: not side by side in order, read field by field
])
def test_lidar_layouts_give_the_json_map(client: TestClient, kit: Any, offsets: tuple[int, int, int], point_step: int,
                                         row_pad: int) -> None:
    ts = store("jazzy")
    points = _cloud_points(n=400, seed=11).astype(np.float32).astype(np.float64)
    # no-returns: one coordinate NaN or infinite, in any axis
    points[np.random.default_rng(5).choice(400, size=50, replace=False), np.arange(50) % 3] = np.resize([np.nan, np.inf, -np.inf], 50)
    msg = cloud_msg(ts, points, height=8, row_pad=row_pad, offsets=offsets, point_step=point_step, dense=False)
    assert (msg.point_step, msg.row_step) == (point_step, 50 * point_step + row_pad)
    position, quaternion = [0.2, -0.1, 1.1], Rotation.from_euler("zx", [0.4, 0.05]).as_quat().tolist()
    client.post("/maps", json=kit.MAP_3D)
    client.post("/maps", json={**kit.MAP_3D, "name": "hall_json"})
    response = _post_cdr(client, "hall", cdr(ts, msg), CLOUD_CT, {**_pose_query(position, quaternion),
                                                                   "range_max": 6.0})
    assert response.status_code == 200, response.text
    finite = points[np.isfinite(points).all(axis=1)]
    assert response.json()["rays"] == finite.shape[0] == 350
    assert _post_json_cloud(client, "hall_json", finite, position, quaternion, 6.0).status_code == 200
    _assert_same_map(client, "hall", "hall_json")


def test_a_dense_float32_cloud_is_read_in_place() -> None:
    # the common lidar layout is viewed in the body's own bytes: a 131,072-point cloud is never copied before
    # fuzzyocc places it (the other layouts, and a cloud with no-returns, are copied once)
    ts = store("jazzy")
    points = _cloud_points(n=64, seed=3).astype(np.float32).astype(np.float64)
    body = cdr(ts, cloud_msg(ts, points, extra=("intensity", "ring")))
    read = messages_in.cloud_points(messages_in.decode(body, messages_in.POINT_CLOUD2), "body", 3,
                                    Limits(max_scans=1, max_rays=100))
    assert np.array_equal(read, points)
    assert np.shares_memory(read, np.frombuffer(body, dtype=np.uint8))
    big_endian = cdr(ts, cloud_msg(ts, points, bigendian=True))
    read = messages_in.cloud_points(messages_in.decode(big_endian, messages_in.POINT_CLOUD2), "body", 3,
                                    Limits(max_scans=1, max_rays=100))
    assert np.array_equal(read, points)
    assert not np.shares_memory(read, np.frombuffer(big_endian, dtype=np.uint8))


def test_pointcloud2_on_a_2d_map_is_rotated_into_the_map_and_projected(client: TestClient, kit: Any) -> None:
    ts = store("jazzy")
    points = _cloud_points(seed=6).astype(np.float32).astype(np.float64)
    quaternion = Rotation.from_euler("zy", [0.8, 0.1]).as_quat()
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps", json={**kit.MAP_2D, "name": "lab_json"})
    response = _post_cdr(client, "lab", cdr(ts, cloud_msg(ts, points)), CLOUD_CT,
                         {**_pose_query([0.5, -0.5, 0.4], quaternion), "range_max": 6.0})
    assert response.status_code == 200, response.text
    planar = Rotation.from_quat(quaternion).apply(points)[:, :2]
    cloud = {"pose": {"x": 0.5, "y": -0.5, "theta": 0.0}, "points": planar.tolist(), "range_max": 6.0}
    assert client.post("/maps/lab_json/scans", json={"scans": [cloud]}).status_code == 200
    _assert_same_map(client, "lab", "lab_json")


@pytest.mark.parametrize("dtype", ["i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"])
def test_every_pointfield_datatype_reads_exactly(dtype: str) -> None:
    ts = store("jazzy")
    points = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12]], dtype=np.float64)
    for bigendian in (False, True):
        msg = ts.deserialize_cdr(cdr(ts, cloud_msg(ts, points, dtype=dtype, bigendian=bigendian)),
                                 "sensor_msgs/msg/PointCloud2")
        read = messages_in.cloud_points(msg, "body", 3, Limits(max_scans=1, max_rays=100))
        assert np.array_equal(read, points)


# ---------------------------------------------------------------- refusals and limits


def _refused(client: TestClient, kit: Any, name: str, body: bytes, content_type: str, params: dict[str, Any],
             status: int) -> str:
    response = _post_cdr(client, name, body, content_type, params)
    assert response.status_code == status, response.text
    assert kit.version(client, name) == 0
    return error_message(response)


def test_refusals_are_4xx_and_change_nothing(client: TestClient, kit: Any) -> None:
    ts = store("jazzy")
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps", json=kit.MAP_3D)
    laser = cdr(ts, laser_msg(ts, wall_ranges()))
    cloud = cdr(ts, cloud_msg(ts, _cloud_points()))
    pose = _pose_query([0, 0, 1], [0, 0, 0, 1])
    cloud_pose = {**pose, "range_max": 6.0}
    assert "not a CDR-serialized" in _refused(client, kit, "lab", laser[:-9], LASER_CT, pose, 422)
    assert "not a CDR-serialized" in _refused(client, kit, "lab", laser[:3], LASER_CT, pose, 422)
    assert "not a CDR-serialized" in _refused(client, kit, "hall", cloud[:200], CLOUD_CT, cloud_pose, 422)
    # cut inside its data, as a dropped connection's body would be
    assert "not a CDR-serialized" in _refused(client, kit, "hall", cloud[:-1000], CLOUD_CT, cloud_pose, 422)
    assert "not a CDR-serialized" in _refused(client, kit, "hall", b"", CLOUD_CT, cloud_pose, 422)
    # the wrong type for the bytes, both ways
    _refused(client, kit, "hall", laser, CLOUD_CT, cloud_pose, 422)
    _refused(client, kit, "lab", cloud, LASER_CT, pose, 422)
    # a message type not read here
    message = _refused(client, kit, "lab", laser, "application/vnd.ros2.sensor_msgs.msg.Image+cdr", pose, 415)
    assert LASER_CT in message and CLOUD_CT in message
    # the pose: all seven numbers, a unit quaternion, nothing the message says itself
    assert "qw" in _refused(client, kit, "lab", laser, LASER_CT, {"x": 0, "y": 0, "z": 0}, 422)
    assert "unit quaternion" in _refused(client, kit, "lab", laser, LASER_CT, {**pose, "qw": 2.0}, 422)
    assert "theta" in _refused(client, kit, "lab", laser, LASER_CT, {**pose, "theta": 0.0}, 422)
    assert "range_max" in _refused(client, kit, "lab", laser, LASER_CT, {**pose, "range_max": 3.0}, 422)
    assert "range_max" in _refused(client, kit, "hall", cloud, CLOUD_CT, pose, 422)
    # missing fields: no z on a 3-D map
    flat = cloud_msg(ts, _cloud_points(), extra=())
    flat.fields = [f for f in flat.fields if f.name != "z"]
    assert "no field z" in _refused(client, kit, "hall", cdr(ts, flat), CLOUD_CT, cloud_pose, 422)
    # sizes that disagree: data shorter than row_step x height, a field past point_step
    short = cloud_msg(ts, _cloud_points())
    short.data = short.data[:-16]
    assert "row_step" in _refused(client, kit, "hall", cdr(ts, short), CLOUD_CT, cloud_pose, 422)
    narrow = cloud_msg(ts, _cloud_points())
    narrow.point_step = 10
    narrow.row_step = 10 * narrow.width
    narrow.data = narrow.data[:10 * narrow.width]
    assert "point_step" in _refused(client, kit, "hall", cdr(ts, narrow), CLOUD_CT, cloud_pose, 422)
    odd = cloud_msg(ts, _cloud_points())
    odd.fields[0].datatype = 9
    assert "datatype" in _refused(client, kit, "hall", cdr(ts, odd), CLOUD_CT, cloud_pose, 422)
    # a NaN in a message field JSON would refuse is refused too
    nan_angle = laser_msg(ts, wall_ranges(), angle_min=float("nan"))
    assert "angle_min" in _refused(client, kit, "lab", cdr(ts, nan_angle), LASER_CT, pose, 422)


def test_sizes_are_checked_against_the_limits(make_client: Any, kit: Any) -> None:
    client = make_client(max_rays_per_scan=250)
    ts = store("jazzy")
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps", json=kit.MAP_3D)
    pose = _pose_query([0, 0, 1], [0, 0, 0, 1])
    laser = cdr(ts, laser_msg(ts, np.full(251, 2.0)))
    assert "FUZZYRISK_MAX_RAYS_PER_SCAN" in _refused(client, kit, "lab", laser, LASER_CT, pose, 413)
    cloud = cdr(ts, cloud_msg(ts, _cloud_points(n=300)))
    assert "FUZZYRISK_MAX_RAYS_PER_SCAN" in _refused(client, kit, "hall", cloud, CLOUD_CT,
                                                      {**pose, "range_max": 6.0}, 413)
    # a header claiming more points than the body holds is refused by its claim, before any read
    claim = bytearray(cloud)
    claim[24:28] = (10**6).to_bytes(4, "little")  # height (after frame_id "lidar\\0", padded to 4 bytes)
    assert "FUZZYRISK_MAX_RAYS_PER_SCAN" in _refused(client, kit, "hall", bytes(claim), CLOUD_CT,
                                                      {**pose, "range_max": 6.0}, 413)


def test_a_body_over_the_byte_limit_is_413(make_client: Any, kit: Any) -> None:
    client = make_client(max_body_bytes=4096)
    ts = store("jazzy")
    client.post("/maps", json=kit.MAP_2D)
    body = cdr(ts, laser_msg(ts, np.full(2000, 2.0)))
    assert len(body) > 4096
    _refused(client, kit, "lab", body, LASER_CT, _pose_query([0, 0, 0], [0, 0, 0, 1]), 413)


def test_both_distributions_define_the_messages_alike() -> None:
    # why one store reads both: the definitions the wire format follows are identical
    humble, jazzy = store("humble"), store("jazzy")
    for msgtype in ("sensor_msgs/msg/LaserScan", "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/PointField",
                    "std_msgs/msg/Header"):
        assert humble.get_msgdef(msgtype).fields == jazzy.get_msgdef(msgtype).fields
