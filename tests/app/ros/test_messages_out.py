"""ROS-shaped outputs: plans as nav_msgs/Path, a frame per map, OccupancyGrid as CDR and
MCAP, the map version on every read, ETags and 304s on the grid routes, stamps of the map's last batch.

The messages are checked with ROS's own definitions through rosbags' typestore: an answer converts to a
genuine ``nav_msgs/msg/Path`` or ``OccupancyGrid`` that serializes to CDR and reads back.
"""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from app.ros import messages_out
from app.config import Settings
from app.api.factory import create_app
from app.storage import SqliteStorage
from tests.conftest import error_message

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
T = TYPESTORE.types
GRID_TYPE = "nav_msgs/msg/OccupancyGrid"


def _time(stamp: dict[str, int]) -> Any:
    return T["builtin_interfaces/msg/Time"](sec=stamp["sec"], nanosec=stamp["nanosec"])


def _header(header: dict[str, Any]) -> Any:
    return T["std_msgs/msg/Header"](stamp=_time(header["stamp"]), frame_id=header["frame_id"])


def _pose(pose: dict[str, Any]) -> Any:
    return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](**pose["position"]),
                                       orientation=T["geometry_msgs/msg/Quaternion"](**pose["orientation"]))


def path_of(answer: dict[str, Any]) -> Any:
    """A genuine nav_msgs/msg/Path from a plan answer, field for field, nothing guessed."""
    return T["nav_msgs/msg/Path"](
        header=_header(answer["header"]),
        poses=[T["geometry_msgs/msg/PoseStamped"](header=_header(p["header"]), pose=_pose(p["pose"]))
               for p in answer["poses"]],
    )


def grid_of(body: dict[str, Any]) -> Any:
    """A genuine nav_msgs/msg/OccupancyGrid from the JSON answer."""
    info = body["info"]
    return T[GRID_TYPE](
        header=_header(body["header"]),
        info=T["nav_msgs/msg/MapMetaData"](map_load_time=_time(info["map_load_time"]), resolution=info["resolution"],
                                           width=info["width"], height=info["height"], origin=_pose(info["origin"])),
        data=np.asarray(body["data"], dtype=np.int8),
    )


def yaw_of(q: Any) -> float:
    assert q.x == 0.0 and q.y == 0.0  # a rotation about +z only (REP 103)
    return 2.0 * math.atan2(q.z, q.w)


def same_angle(a: float, b: float, tol: float = 1e-9) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) <= tol


def ros_time(iso: str) -> dict[str, int]:
    when = datetime.fromisoformat(iso)  # "Z" too (Python 3.11)
    micros = round((when - datetime(1970, 1, 1, tzinfo=UTC)).total_seconds() * 1e6)
    return {"sec": micros // 1_000_000, "nanosec": micros % 1_000_000 * 1000}


# ---------------------------------------------------------------- plans as nav_msgs/Path


@pytest.fixture(scope="module")
def planner(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """A service with ``lab`` (frame robot1/map, a wall at x = 3.05 m) and the 3-D ``hall`` (frame map)."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("ros"), plan_workers=1, max_plan_time_s=5.0)
    with TestClient(create_app(settings)) as client:
        client.post("/maps", json={"name": "lab", "resolution": 0.1, "origin": [-5.0, -5.0], "size": [10.0, 10.0],
                                   "frame_id": "robot1/map"})
        angles = -math.pi / 4 + np.arange(181) * (math.pi / 2 / 180)
        scan = {"pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -math.pi / 4,
                "angle_increment": math.pi / 2 / 180, "ranges": (3.05 / np.cos(angles)).tolist(),
                "range_min": 0.1, "range_max": 20.0}
        assert client.post("/maps/lab/scans", json={"scans": [scan]}).status_code == 200
        client.post("/maps", json={"name": "hall", "resolution": 0.2, "origin": [-4.0, -4.0, 0.0],
                                   "size": [8.0, 8.0, 3.0]})
        yield client


def _plan(client: TestClient, name: str = "lab", **body: Any) -> dict[str, Any]:
    request = {"start": [-1.5, -1.0], "goal": [2.0, 1.5], "planner": "RRTConnect", "time_limit": 1.0,
               "robot_radius": 0.1, "seed": 3, **body}
    before = datetime.now(UTC)
    response = client.post(f"/maps/{name}/plan", json=request)
    assert response.status_code == 200, response.text
    answer = response.json()
    assert response.headers["X-Map-Version"] == str(answer["version"])
    stamp = answer["header"]["stamp"]
    made = stamp["sec"] + stamp["nanosec"] * 1e-9
    assert before.timestamp() - 1e-3 <= made <= datetime.now(UTC).timestamp()  # when the plan was made
    return answer


def _to_path(answer: dict[str, Any]) -> Any:
    """The answer as a nav_msgs/msg/Path, through CDR and back: what a ROS node would receive."""
    message = path_of(answer)
    cdr = TYPESTORE.serialize_cdr(message, "nav_msgs/msg/Path")
    back = TYPESTORE.deserialize_cdr(bytes(cdr), "nav_msgs/msg/Path")
    assert back == message
    for pose in back.poses:
        q = pose.pose.orientation
        assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, abs_tol=1e-12)  # unit
        assert pose.header == back.header  # every pose carries the path's header, as Nav2's planners write
    return back


def test_an_r2_plan_is_a_nav_msgs_path_headed_along_the_path(planner: TestClient) -> None:
    answer = _plan(planner)
    path = _to_path(answer)
    assert path.header.frame_id == "robot1/map"
    points = np.asarray(answer["path"])
    assert len(path.poses) == len(points) >= 2
    assert [(p.pose.position.x, p.pose.position.y, p.pose.position.z) for p in path.poses] == \
        [(x, y, 0.0) for x, y in points]
    yaws = [yaw_of(p.pose.orientation) for p in path.poses]
    for k in range(len(points) - 1):  # each pose faces the next point
        dx, dy = points[k + 1] - points[k]
        assert same_angle(yaws[k], math.atan2(dy, dx))
    assert same_angle(yaws[-1], yaws[-2])  # the last keeps the heading of the step before it


def test_goal_yaw_orients_the_last_pose_of_an_r2_path(planner: TestClient) -> None:
    plain, turned = _plan(planner), _plan(planner, goal_yaw=-2.0)
    assert turned["path"] == plain["path"]  # the planner never sees goal_yaw
    poses = _to_path(turned).poses
    assert same_angle(yaw_of(poses[-1].pose.orientation), -2.0)
    assert [p.pose.orientation for p in poses[:-1]] == [p.pose.orientation for p in _to_path(plain).poses[:-1]]


@pytest.mark.parametrize("space", ["SE2", "Dubins", "ReedsShepp"])
def test_a_car_plan_carries_the_planned_yaw(planner: TestClient, space: str) -> None:
    extra = {} if space == "SE2" else {"turning_radius": 0.5}
    answer = _plan(planner, start=[-1.5, -1.0, 0.3], goal=[2.0, 1.5, 1.2], state_space=space, **extra)
    path = _to_path(answer)
    assert path.header.frame_id == "robot1/map"
    for pose, (x, y, theta) in zip(path.poses, answer["path"], strict=True):
        assert (pose.pose.position.x, pose.pose.position.y, pose.pose.position.z) == (x, y, 0.0)
        assert same_angle(yaw_of(pose.pose.orientation), theta)
    assert same_angle(yaw_of(path.poses[0].pose.orientation), 0.3)


def test_goal_yaw_is_refused_where_the_goal_has_a_yaw(planner: TestClient) -> None:
    response = planner.post("/maps/lab/plan", json={"start": [-1.5, -1.0, 0.0], "goal": [2.0, 1.5, 0.0],
                                                     "state_space": "SE2", "goal_yaw": 1.0})
    assert response.status_code == 422
    assert "third value" in error_message(response)


def test_an_r3_plan_is_headed_over_the_ground_at_its_own_height(planner: TestClient) -> None:
    answer = _plan(planner, name="hall", start=[-2.0, -2.0, 0.5], goal=[2.0, 1.0, 2.0])
    path = _to_path(answer)
    assert path.header.frame_id == "map"  # the default frame
    points = np.asarray(answer["path"])
    assert [p.pose.position.z for p in path.poses] == points[:, 2].tolist()
    yaws = [yaw_of(p.pose.orientation) for p in path.poses]
    for k in range(len(points) - 1):
        dx, dy = points[k + 1, :2] - points[k, :2]
        if math.hypot(dx, dy) > 1e-9:
            assert same_angle(yaws[k], math.atan2(dy, dx))


def test_a_plan_that_misses_the_goal_still_has_a_header_and_one_pose_a_point(planner: TestClient) -> None:
    # behind the wall, a millisecond of a car's sampling: approximate or none (test_plans)
    answer = planner.post("/maps/lab/plan", json={"start": [-1.5, 0.0, 0.0], "goal": [4.5, 0.0, 0.0],
                                                  "state_space": "Dubins", "turning_radius": 0.5,
                                                  "time_limit": 0.001}).json()
    assert answer["status"] in ("approximate", "none") and len(answer["poses"]) == len(answer["path"])
    assert _to_path(answer).header.frame_id == "robot1/map"


def test_path_yaws_keep_a_heading_through_repeated_and_vertical_points() -> None:
    path = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 2.0]])
    assert np.allclose(messages_out.path_yaws(path, "R3"), [math.pi / 4] * 5)  # vertical and repeated steps keep it
    assert np.allclose(messages_out.path_yaws(path[:1], "R2"), [0.0])  # one point: identity
    assert np.allclose(messages_out.path_yaws(path[:1], "R2", goal_yaw=1.0), [1.0])
    assert np.allclose(messages_out.path_yaws(np.array([[0.0, 0.0], [0.0, -1.0]]), "R2", goal_yaw=0.5), [-math.pi / 2, 0.5])


# ---------------------------------------------------------------- frame per map


@pytest.mark.parametrize("frame_id", ["/map", "map/", "robot1//map", "1map", "ro bot/map", "map.1", "", "a" * 257])
def test_a_frame_id_ros_would_refuse_answers_422(client: TestClient, kit: Any, frame_id: str) -> None:
    response = client.post("/maps", json={**kit.MAP_2D, "frame_id": frame_id})
    assert response.status_code == 422
    assert "frame_id" in error_message(response) and "robot1/map" in error_message(response)  # says the rule
    assert client.get("/maps").json() == []


def test_the_frame_is_kept_and_used_in_every_output_that_has_one(make_client: Any, kit: Any) -> None:
    client = make_client()
    info = client.post("/maps", json={**kit.MAP_2D, "frame_id": "robot_2/map"}).json()
    assert info["frame_id"] == "robot_2/map"
    assert client.post("/maps", json={**kit.MAP_2D, "name": "plain"}).json()["frame_id"] == "map"
    client.post("/maps/lab/scans", json={"scans": [kit.laser()]})

    def outputs(c: TestClient) -> list[str]:
        cdr = c.get("/maps/lab/occupancy_grid", params={"format": "cdr"}).content
        npy = c.get("/maps/lab/risk", params={"format": "npy"})
        with zipfile.ZipFile(io.BytesIO(c.get("/maps/lab/export/nav2").content)) as archive:
            yaml_text = archive.read("map.yaml").decode()
        return [c.get("/maps/lab").json()["frame_id"],
                c.get("/maps/lab/occupancy_grid").json()["header"]["frame_id"],
                TYPESTORE.deserialize_cdr(cdr, GRID_TYPE).header.frame_id,
                c.get("/maps/lab/risk").json()["frame_id"], npy.headers["X-Map-Frame"],
                yaml_text.splitlines()[0].split()[2]]

    assert outputs(client) == ["robot_2/map"] * 6
    client.__exit__(None, None, None)
    assert outputs(make_client()) == ["robot_2/map"] * 6  # stored with the map


def test_a_map_stored_before_frames_reads_as_map(make_settings: Any, make_client: Any, kit: Any) -> None:
    # the meta and the batch exactly as the service wrote them before maps had a frame
    storage = SqliteStorage(make_settings().database_path)
    old_meta = {key: kit.MAP_2D[key] for key in ("name", "origin", "size", "resolution", "model", "sensor")}
    now = datetime.now(UTC).isoformat(timespec="milliseconds")
    storage.create_map("lab", {**old_meta, "created": now}, now)
    storage.close()

    client = make_client()
    assert client.get("/maps/lab").json()["frame_id"] == "map"
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200
    grid = client.get("/maps/lab/occupancy_grid", params={"format": "cdr"})
    assert TYPESTORE.deserialize_cdr(grid.content, GRID_TYPE).header.frame_id == "map"
    assert grid.headers["X-Map-Version"] == "1"


# ---------------------------------------------------------------- OccupancyGrid as CDR and MCAP


@pytest.fixture
def scanned(lab: TestClient, kit: Any) -> TestClient:
    scans = [kit.laser(wall=3.05), kit.laser(x=-2.0, y=-3.0, theta=math.pi / 2, wall=6.05)]
    assert lab.post("/maps/lab/scans", json={"scans": scans}).status_code == 200
    return lab


@pytest.mark.parametrize("mode", ["trinary", "scale", "probability"])
def test_the_cdr_grid_is_the_json_grid_serialized_as_ros_does(scanned: TestClient, mode: str) -> None:
    body = scanned.get("/maps/lab/occupancy_grid", params={"mode": mode}).json()
    response = scanned.get("/maps/lab/occupancy_grid", params={"mode": mode, "format": "cdr"})
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/vnd.ros2.nav_msgs.msg.OccupancyGrid+cdr"
    assert response.content[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation, as rclpy writes
    assert response.content == bytes(TYPESTORE.serialize_cdr(grid_of(body), GRID_TYPE))
    message = TYPESTORE.deserialize_cdr(response.content, GRID_TYPE)
    assert message.data.tolist() == body["data"] and message.info.width == body["info"]["width"] == 100
    assert body["version"] == 1 and response.headers["X-Map-Version"] == "1"


def test_the_mcap_file_holds_one_grid_on_map_for_rosbags_and_mcap_readers(scanned: TestClient,
                                                                         tmp_path: Path) -> None:
    cdr = scanned.get("/maps/lab/occupancy_grid", params={"format": "cdr"}).content
    response = scanned.get("/maps/lab/occupancy_grid", params={"format": "mcap"})
    assert response.status_code == 200 and response.headers["content-type"] == "application/mcap"
    stamp = TYPESTORE.deserialize_cdr(cdr, GRID_TYPE).header.stamp
    stamp_ns = stamp.sec * 1_000_000_000 + stamp.nanosec

    reader = make_reader(io.BytesIO(response.content))
    assert reader.get_header().profile == "ros2"
    read = [(schema.name, schema.encoding, channel.topic, channel.message_encoding, message.log_time, message.data)
            for schema, channel, message in reader.iter_messages()]
    assert read == [(GRID_TYPE, "ros2msg", "/map", "cdr", stamp_ns, cdr)]

    path = tmp_path / "lab.mcap"
    path.write_bytes(response.content)
    with Reader(path) as bag:
        assert [(c.topic, c.msgtype, c.msgcount) for c in bag.connections] == [("/map", GRID_TYPE, 1)]
        qos = bag.connections[0].ext.offered_qos_profiles
        assert [q.durability.name for q in qos] == ["TRANSIENT_LOCAL"]  # latched, as map_server publishes
        [(connection, timestamp, data)] = list(bag.messages())
        assert timestamp == stamp_ns and bytes(data) == cdr
        # the stored definition is enough to read it (what a reader without our typestore does)
        store = get_typestore(Stores.EMPTY)
        store.register(get_types_from_msg(connection.msgdef.data, GRID_TYPE))
        assert store.deserialize_cdr(data, GRID_TYPE).data.tolist() == \
            TYPESTORE.deserialize_cdr(cdr, GRID_TYPE).data.tolist()


# ---------------------------------------------------------------- versions, stamps, ETags

GRID_READS = [
    ("/maps/lab/risk", {}), ("/maps/lab/risk", {"format": "npy"}), ("/maps/lab/risk", {"format": "npy", "layer":
    "observed"}), ("/maps/lab/risk", {"format": "png", "scale": 2}),
    ("/maps/lab/occupancy_grid", {}), ("/maps/lab/occupancy_grid", {"format": "cdr"}),
    ("/maps/lab/occupancy_grid", {"format": "mcap"}), ("/maps/lab/occupancy_grid", {"mode": "probability"}),
    ("/maps/lab/export/nav2", {}), ("/maps/lab/export/nav2", {"mode": "scale", "format": "png"}),
]


def test_every_map_read_carries_the_version(scanned: TestClient) -> None:
    for path, params in GRID_READS:
        assert scanned.get(path, params=params).headers["X-Map-Version"] == "1", (path, params)
    assert scanned.get("/maps/lab").headers["X-Map-Version"] == "1"
    assert scanned.get("/maps/lab/scans/last").headers["X-Map-Version"] == "1"
    assert scanned.post("/maps/lab/risk/query", json={"points": [[0, 0]]}).headers["X-Map-Version"] == "1"


def test_repeated_reads_of_a_version_are_the_same_bytes_and_etag(make_client: Any, kit: Any) -> None:
    client = make_client()
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps/lab/scans", json={"scans": [kit.laser()]})
    first = {(p, tuple(q.items())): client.get(p, params=q) for p, q in GRID_READS}
    etags = [r.headers["ETag"] for r in first.values()]
    assert len(set(etags)) == len(etags)  # each format and query has its own
    assert all(e.startswith('"v1-') and e.endswith('"') for e in etags)  # strong, and naming the version
    for (p, q), r in first.items():
        again = client.get(p, params=dict(q))
        assert (again.content, again.headers["ETag"]) == (r.content, r.headers["ETag"]), p
    client.__exit__(None, None, None)
    restarted = make_client()  # replayed from the store: the same bytes, the same tags
    for (p, q), r in first.items():
        again = restarted.get(p, params=dict(q))
        assert (again.content, again.headers["ETag"]) == (r.content, r.headers["ETag"]), p


def test_if_none_match_answers_304_until_the_map_changes(scanned: TestClient, kit: Any) -> None:
    for path, params in GRID_READS:
        etag = scanned.get(path, params=params).headers["ETag"]
        for header in (etag, f"W/{etag}", f'"other", {etag}', "*"):
            unchanged = scanned.get(path, params=params, headers={"If-None-Match": header})
            assert unchanged.status_code == 304 and unchanged.content == b"", (path, params, header)
            assert unchanged.headers["ETag"] == etag and unchanged.headers["X-Map-Version"] == "1"
        assert scanned.get(path, params=params, headers={"If-None-Match": '"v1-other"'}).status_code == 200
    etags = {(p, tuple(q.items())): scanned.get(p, params=q).headers["ETag"] for p, q in GRID_READS}
    assert scanned.post("/maps/lab/scans", json={"scans": [kit.laser(y=1.0)]}).status_code == 200
    for (path, params), etag in etags.items():
        changed = scanned.get(path, params=dict(params), headers={"If-None-Match": etag})
        assert changed.status_code == 200 and changed.headers["X-Map-Version"] == "2"
        assert changed.headers["ETag"] != etag and changed.headers["ETag"].startswith('"v2-')


def test_a_map_made_again_under_its_name_has_new_etags(lab: TestClient, kit: Any) -> None:
    etag = lab.get("/maps/lab/occupancy_grid").headers["ETag"]
    lab.delete("/maps/lab")
    lab.post("/maps", json={**kit.MAP_2D, "frame_id": "other"})  # version 0 again, another map
    again = lab.get("/maps/lab/occupancy_grid", headers={"If-None-Match": etag})
    assert again.status_code == 200 and again.json()["header"]["frame_id"] == "other"


def test_the_grid_stamp_is_the_time_of_the_maps_last_batch(lab: TestClient, kit: Any) -> None:
    info = lab.get("/maps/lab").json()
    header = lab.get("/maps/lab/occupancy_grid").json()
    assert header["header"]["stamp"] == header["info"]["map_load_time"] == ros_time(info["created"])
    lab.post("/maps/lab/scans", json={"scans": [kit.laser()]})
    info = lab.get("/maps/lab").json()
    grid = lab.get("/maps/lab/occupancy_grid", params={"format": "cdr"}).content
    message = TYPESTORE.deserialize_cdr(grid, GRID_TYPE)
    assert ros_time(info["updated"]) == {"sec": message.header.stamp.sec, "nanosec": message.header.stamp.nanosec}
    assert message.info.map_load_time == message.header.stamp and info["updated"] != info["created"]


def test_an_occupancy_grid_too_big_for_json_is_refused_with_the_binary_ways_named(client: TestClient,
                                                                                  kit: Any) -> None:
    # two readers of a 16 M-cell JSON OccupancyGrid held the GIL 1-3 s a read, stalling every client
    big = {**kit.MAP_2D, "name": "hall", "origin": [0.0, 0.0], "size": [205.0, 205.0]}  # 2050 x 2050 cells
    assert client.post("/maps", json=big).status_code == 201
    refused = client.get("/maps/hall/occupancy_grid")
    assert refused.status_code == 422
    assert "4,000,000" in error_message(refused) and "occupancy_grid.cdr" in error_message(refused)
    cdr = client.get("/maps/hall/occupancy_grid.cdr")
    assert cdr.status_code == 200 and len(cdr.content) > 2050 * 2050
    small = {**kit.MAP_2D, "name": "room", "origin": [0.0, 0.0], "size": [200.0, 200.0]}  # 4 M cells: still JSON
    assert client.post("/maps", json=small).status_code == 201
    assert len(client.get("/maps/room/occupancy_grid").json()["data"]) == 2000 * 2000


@pytest.mark.parametrize("cells", [0, 1, 3, 4, 7, 12_345])
def test_the_grid_is_serialized_as_rosbags_serializes_it_whole(cells: int) -> None:
    # the cells are appended to rosbags' serialization of the rest (one copy of 16 M cells instead of three)
    import numpy as np

    from app.ros import messages_out
    from app.ros.msgtypes import typestore

    data = np.random.default_rng(cells).integers(-1, 101, cells).astype(np.int8)
    message = messages_out.occupancy_grid_message(data, width=cells, height=1 if cells else 0, resolution=0.05,
                                            origin_xy=(-1.5, 2.25), frame_id="map", stamp={"sec": 7, "nanosec": 9})
    whole = bytes(typestore().serialize_cdr(message, messages_out.OCCUPANCY_GRID))
    assert messages_out.occupancy_grid_cdr(message) == whole
