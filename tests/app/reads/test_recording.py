"""The MCAP export of a map: its grid and the scans of its batch log, for offline viewing.

The file is read twice, as a viewer would: with the ``mcap`` package's reader (topics, schemas, log
times, the raw CDR) and with rosbags' ``AnyReader`` (a single ``.mcap`` file; messages deserialized
from the definitions stored in the file, not from our typestore).
"""

from __future__ import annotations

import io
import math
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from app.reads import recording
from tests.conftest import error_message

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
GRID, SCAN, TF, CLOUD = ("nav_msgs/msg/OccupancyGrid", "sensor_msgs/msg/LaserScan", "tf2_msgs/msg/TFMessage",
                         "sensor_msgs/msg/PointCloud2")
NS = 1_000_000_000


def ns_of_iso(text: str) -> int:
    """Unix nanoseconds of the service's ``updated`` (milliseconds: exact in a float of microseconds)."""
    when = datetime.fromisoformat(text)
    return round(when.timestamp() * 1_000_000) * 1000


def stamp_ns(header: Any) -> int:
    return header.stamp.sec * NS + header.stamp.nanosec


def mcap_messages(data: bytes) -> list[tuple[str, str, int, Any]]:
    """(topic, schema, log time, message deserialized with our typestore) in the file's log-time order."""
    reader = make_reader(io.BytesIO(data))
    assert reader.get_header().profile == "ros2"
    out = []
    for schema, channel, message in reader.iter_messages(log_time_order=True):
        assert (schema.encoding, channel.message_encoding) == ("ros2msg", "cdr")
        out.append((channel.topic, schema.name, message.log_time, TYPESTORE.deserialize_cdr(message.data, schema.name)))
    return out


def export(client: TestClient, name: str, **headers: str) -> Any:
    response = client.get(f"/maps/{name}/export/mcap", headers=headers)
    assert response.status_code == 200, response.text
    return response


def two_laser_batches(kit: Any) -> list[dict[str, Any]]:
    """Two batches: LaserScans whose ranges hold no-returns (+inf), an invalid reading (null) and -inf."""
    first = [kit.laser(wall=3.05), kit.laser(x=-1.0, y=0.5, theta=0.7, wall=2.0)]
    first[0]["ranges"][3], first[0]["ranges"][4], first[0]["ranges"][5] = "inf", None, "-inf"
    second = [kit.laser(x=1.0, y=-2.0, theta=-2.5, wall=4.2, beams=33)]
    return [{"scans": first}, {"scans": second}]


@pytest.fixture
def lasers(lab: TestClient, kit: Any) -> tuple[TestClient, list[dict[str, Any]]]:
    posted = []
    for batch in two_laser_batches(kit):
        assert lab.post("/maps/lab/scans", json=batch).status_code == 200
        posted += batch["scans"]
    return lab, posted


# ---------------------------------------------------------------- 2-D: LaserScans, their transforms, the grid


def test_a_2d_map_records_each_laser_scan_with_its_transform_and_the_grid(
        lasers: tuple[TestClient, list[dict[str, Any]]]) -> None:
    client, posted = lasers
    response = export(client, "lab")
    assert response.headers["content-type"] == "application/mcap"
    assert response.headers["X-Map-Version"] == "2" and response.headers[recording.SINCE_HEADER] == "0"
    assert response.headers["Content-Disposition"] == 'attachment; filename="lab-v2.mcap"'
    read = mcap_messages(response.content)
    topics = [topic for topic, *_ in read]
    assert topics.count("/map") == 1 and topics.count("/scan") == topics.count("/tf") == 3
    assert set(topics) == {"/map", "/scan", "/tf"}  # no cloud posted: no /points channel

    scans = [m for topic, _, _, m in read if topic == "/scan"]
    tfs = [m for topic, _, _, m in read if topic == "/tf"]
    for scan, transform, sent in zip(scans, tfs, posted, strict=True):
        # ranges bit for bit as posted (float32): +inf no return, NaN, -inf kept as REP 117 has them
        expected = np.array(sent["ranges"], dtype=np.float64).astype(np.float32)
        assert scan.ranges.dtype == np.float32
        np.testing.assert_array_equal(scan.ranges.view(np.uint32), expected.view(np.uint32))
        assert scan.header.frame_id == "map_laser"
        assert scan.angle_min == np.float32(sent["angle_min"])
        assert scan.angle_increment == np.float32(sent["angle_increment"])
        assert scan.angle_max == pytest.approx(sent["angle_min"] + (len(sent["ranges"]) - 1) * sent["angle_increment"])
        assert (scan.range_min, scan.range_max) == (np.float32(sent["range_min"]), np.float32(sent["range_max"]))
        # the transform puts the sensor at the posted pose, at the scan's stamp
        (stamped,) = transform.transforms
        assert (stamped.header.frame_id, stamped.child_frame_id) == ("map", "map_laser")
        assert stamp_ns(stamped.header) == stamp_ns(scan.header)
        t, q = stamped.transform.translation, stamped.transform.rotation
        pose = sent["pose"]
        assert (t.x, t.y, t.z) == (pose["x"], pose["y"], 0.0)
        yaw = 2 * math.atan2(q.z, q.w)
        assert (q.x, q.y) == (0.0, 0.0)
        assert math.remainder(yaw - pose["theta"], 2 * math.pi) == pytest.approx(0, abs=1e-12)

    # the grid: the bytes occupancy_grid.cdr answers
    cdr = client.get("/maps/lab/occupancy_grid.cdr").content
    reader = make_reader(io.BytesIO(response.content))
    (grid_bytes,) = [m.data for _, c, m in reader.iter_messages() if c.topic == "/map"]
    assert grid_bytes == cdr


def test_stamps_end_at_the_maps_updated_time_a_tenth_of_a_second_apart(
        lasers: tuple[TestClient, list[dict[str, Any]]]) -> None:
    client, _ = lasers
    read = mcap_messages(export(client, "lab").content)
    updated = ns_of_iso(client.get("/maps/lab").json()["updated"])
    scan_times = [(log_time, stamp_ns(m.header)) for topic, _, log_time, m in read if topic == "/scan"]
    assert [stamp for _, stamp in scan_times] == [updated - 2 * NS // 10, updated - NS // 10, updated]
    assert all(log_time == stamp for log_time, stamp in scan_times)
    # the grid is stamped as occupancy_grid.cdr (the map's updated time), logged with the first scan
    ((_, _, grid_log_time, grid),) = [r for r in read if r[0] == "/map"]
    assert stamp_ns(grid.header) == updated and grid_log_time == scan_times[0][0]
    assert read[0][0] == "/map"


def test_rosbags_reads_the_file_from_its_own_definitions(lasers: tuple[TestClient, list[dict[str, Any]]],
                                                         tmp_path: Path) -> None:
    client, posted = lasers
    path = tmp_path / "lab.mcap"
    path.write_bytes(export(client, "lab").content)
    with AnyReader([path]) as reader:  # a single .mcap file: no metadata.yaml needed
        counts = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        assert counts == {"/map": (GRID, 1), "/scan": (SCAN, 3), "/tf": (TF, 3)}
        qos = {c.topic: [q.durability.name for q in c.ext.offered_qos_profiles] for c in reader.connections}
        assert qos == {"/map": ["TRANSIENT_LOCAL"], "/scan": ["VOLATILE"], "/tf": ["VOLATILE"]}
        scans = [reader.deserialize(data, c.msgtype)
                 for c, _, data in reader.messages(connections=[c for c in reader.connections if c.topic == "/scan"])]
    for scan, sent in zip(scans, posted, strict=True):
        expected = np.array(sent["ranges"], dtype=np.float64).astype(np.float32)
        np.testing.assert_array_equal(np.asarray(scan.ranges).view(np.uint32), expected.view(np.uint32))


def test_a_2d_point_cloud_is_recorded_in_the_map_frame(lab: TestClient, kit: Any) -> None:
    points_sensor = [[2.0, -0.5], [2.0, 0.0], [2.5, 0.25], [None, 1.0]]  # the last row: no return, dropped
    pose = {"x": 0.5, "y": -1.0, "theta": 0.4}
    body = {"scans": [kit.laser(), {"pose": pose, "points": points_sensor, "range_max": 10.0}]}
    assert lab.post("/maps/lab/scans", json=body).status_code == 200
    read = mcap_messages(export(lab, "lab").content)
    assert [topic for topic, *_ in read] == ["/map", "/tf", "/scan", "/points"]
    cloud = read[-1][3]
    assert cloud.header.frame_id == "map" and (cloud.height, cloud.width, cloud.point_step) == (1, 3, 12)
    assert [(f.name, f.offset, f.datatype) for f in cloud.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    xyz = np.frombuffer(cloud.data.tobytes(), dtype="<f4").reshape(-1, 3)
    c, s = math.cos(pose["theta"]), math.sin(pose["theta"])  # as app.scans.scan puts the points in the map frame
    expected = np.array(points_sensor[:3]) @ np.array([[c, -s], [s, c]]).T + [pose["x"], pose["y"]]
    np.testing.assert_array_equal(xyz[:, :2], expected.astype(np.float32))
    assert not xyz[:, 2].any()


# ---------------------------------------------------------------- 3-D: point clouds


def test_a_3d_map_records_its_clouds_points_in_the_map_frame(client: TestClient, kit: Any, tmp_path: Path) -> None:
    assert client.post("/maps", json=kit.MAP_3D).status_code == 201
    posted = []
    for yaw, position in ((0.3, [0.5, -0.25, 1.0]), (-1.2, [-1.0, 1.5, 0.75])):
        points = kit.cloud_sensor_points(50)
        quaternion = Rotation.from_euler("z", yaw).as_quat().tolist()
        scan = {"pose": {"position": position, "orientation": quaternion}, "points": points.tolist(),
                "range_max": 6.0}
        assert client.post("/maps/hall/scans", json={"scans": [scan]}).status_code == 200
        # the map-frame points, computed as fuzzyocc's PointCloud.from_sensor_frame does
        rotation = Rotation.from_quat(np.array(quaternion) / np.linalg.norm(quaternion))
        posted.append(rotation.apply(points) + np.array(position))
    response = export(client, "hall")
    read = mcap_messages(response.content)
    assert [topic for topic, *_ in read] == ["/map", "/points", "/points"]
    for (_, schema, _, cloud), expected in zip(read[1:], posted, strict=True):
        assert schema == CLOUD and cloud.header.frame_id == "map" and cloud.is_dense
        xyz = np.frombuffer(cloud.data.tobytes(), dtype="<f4").reshape(-1, 3)
        np.testing.assert_array_equal(xyz, expected.astype(np.float32))
    # the grid of a 3-D map: its projection, as occupancy_grid.cdr gives it
    assert [m.data for _, c, m in make_reader(io.BytesIO(response.content)).iter_messages() if c.topic == "/map"] \
        == [client.get("/maps/hall/occupancy_grid.cdr").content]
    path = tmp_path / "hall.mcap"
    path.write_bytes(response.content)
    with AnyReader([path]) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == {"/map": 1, "/points": 2}
        clouds = [reader.deserialize(data, c.msgtype) for c, _, data in reader.messages()
                  if c.topic == "/points"]
    assert [c.width for c in clouds] == [50, 50]


# ---------------------------------------------------------------- versions, snapshots, bounds


def test_repeated_reads_are_the_same_bytes_and_etag_and_a_match_is_304(
        lasers: tuple[TestClient, list[dict[str, Any]]], kit: Any) -> None:
    client, _ = lasers
    first, second = export(client, "lab"), export(client, "lab")
    assert first.content == second.content and first.headers["ETag"] == second.headers["ETag"]
    same = client.get("/maps/lab/export/mcap", headers={"If-None-Match": first.headers["ETag"]})
    assert same.status_code == 304 and same.content == b""
    assert same.headers["X-Map-Version"] == "2" and same.headers[recording.SINCE_HEADER] == "0"
    # a generic client that accepts only octet-stream: the same bytes, labelled so, under a tag of their own
    generic = export(client, "lab", accept="application/octet-stream")
    assert generic.headers["content-type"] == "application/octet-stream" and generic.content == first.content
    assert generic.headers["ETag"] != first.headers["ETag"]
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200
    later = client.get("/maps/lab/export/mcap", headers={"If-None-Match": first.headers["ETag"]})
    assert later.status_code == 200 and later.headers["ETag"] != first.headers["ETag"]
    assert [t for t, *_ in mcap_messages(later.content)].count("/scan") == 4


def test_after_a_snapshot_only_the_later_scans_are_recorded(make_client: Any, kit: Any) -> None:
    client = make_client(snapshot_every=2)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    walls = [3.0, 3.5, 4.0]
    for wall in walls:  # versions 1, 2 (then a snapshot at 2), 3
        assert client.post("/maps/lab/scans", json={"scans": [kit.laser(wall=wall)]}).status_code == 200
    kit.snapshots_stored(client)
    response = export(client, "lab")
    assert response.headers[recording.SINCE_HEADER] == "2" and response.headers["X-Map-Version"] == "3"
    scans = [m for topic, _, _, m in mcap_messages(response.content) if topic == "/scan"]
    assert len(scans) == 1
    expected = np.array(kit.laser(wall=walls[-1])["ranges"], dtype=np.float32)
    np.testing.assert_array_equal(scans[0].ranges, expected)
    # the snapshot after the 4th batch empties the log: only the grid, since version 4
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser(wall=5.0)]}).status_code == 200
    kit.snapshots_stored(client)
    emptied = export(client, "lab")
    assert emptied.headers[recording.SINCE_HEADER] == "4"
    assert [topic for topic, *_ in mcap_messages(emptied.content)] == ["/map"]


def test_a_new_map_records_its_grid_alone(lab: TestClient) -> None:
    response = export(lab, "lab")
    ((topic, _, log_time, grid),) = mcap_messages(response.content)
    assert topic == "/map" and log_time == stamp_ns(grid.header) == ns_of_iso(lab.get("/maps/lab").json()["updated"])
    assert response.headers[recording.SINCE_HEADER] == "0" and response.headers["X-Map-Version"] == "0"


def test_a_log_larger_than_the_bound_is_refused_naming_it(make_client: Any, kit: Any) -> None:
    client = make_client(max_recording_bytes=12_000)  # the 100 x 100 grid (10 kB) and not much more
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    assert client.get("/maps/lab/export/mcap").status_code == 200
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser(beams=1000)]}).status_code == 200
    refused = client.get("/maps/lab/export/mcap")
    assert refused.status_code == 413 and refused.json()["code"] == "TOO_LARGE"
    assert "FUZZYRISK_MAX_RECORDING_BYTES" in error_message(refused)


def test_an_unknown_map_is_404(client: TestClient) -> None:
    response = client.get("/maps/nope/export/mcap")
    assert response.status_code == 404 and response.json()["code"] == "NOT_FOUND"
