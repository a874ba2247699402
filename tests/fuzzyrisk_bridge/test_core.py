"""The ROS 2 bridge's core (fuzzyrisk_bridge.core) below the rclpy subscription.

Messages are genuine ROS 2 messages built by the rosbags typestore. The service is the real one,
served by uvicorn in a thread of this process; the retry and timeout cases that need an answer
the service does not give on demand (a 429, a Retry-After of an hour, a stalled answer) use a
tiny scripted HTTP server. Every thread a test starts ends with it.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import httpx
import numpy as np
import pytest
import uvicorn
from rosbags.typesys import Stores, get_typestore

from app.config import Settings
from app.errors import Invalid
from app.ops.process_setup import bind
from app.api.factory import create_app
from app.ros.messages_in import SensorPose, level_heading
from fuzzyrisk_bridge import __main__ as bridge_main
from fuzzyrisk_bridge.core import Bridge, BridgeConfig, NotLevel, scan_to_json

TYPES = get_typestore(Stores.ROS2_JAZZY).types
Time = TYPES["builtin_interfaces/msg/Time"]
Header = TYPES["std_msgs/msg/Header"]
LaserScanMsg = TYPES["sensor_msgs/msg/LaserScan"]
TransformStamped = TYPES["geometry_msgs/msg/TransformStamped"]
Transform = TYPES["geometry_msgs/msg/Transform"]
Vector3 = TYPES["geometry_msgs/msg/Vector3"]
Quaternion = TYPES["geometry_msgs/msg/Quaternion"]

MAP = {"name": "lab", "resolution": 0.1, "origin": [-5.0, -5.0], "size": [10.0, 10.0]}
BEAMS = 91


def laser_msg(stamp_s: float = 0.0, ranges: np.ndarray | None = None, frame: str = "laser") -> Any:
    """A LaserScan facing a wall 3 m ahead, +-45 degrees (the service tests' ``kit.laser``)."""
    angle_min, increment = -math.pi / 4, (math.pi / 2) / (BEAMS - 1)
    if ranges is None:
        ranges = (3.0 / np.cos(angle_min + increment * np.arange(BEAMS))).astype(np.float32)
    sec = int(stamp_s)
    return LaserScanMsg(
        header=Header(stamp=Time(sec=sec, nanosec=int((stamp_s - sec) * 1e9)), frame_id=frame),
        angle_min=angle_min, angle_max=angle_min + increment * (len(ranges) - 1), angle_increment=increment,
        time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=20.0,
        ranges=np.asarray(ranges, dtype=np.float32), intensities=np.zeros(0, dtype=np.float32),
    )


def tf_msg(x: float, y: float, yaw: float, *, roll: float = 0.0) -> Any:
    """``T_map_laser`` as tf2 hands it over: a TransformStamped (rotation = yaw about z, then roll about x)."""
    cy, sy, cr, sr = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(roll / 2), math.sin(roll / 2)
    q = Quaternion(x=cy * sr, y=sy * sr, z=sy * cr, w=cy * cr)  # q_z(yaw) * q_x(roll)
    return TransformStamped(header=Header(stamp=Time(sec=0, nanosec=0), frame_id="map"), child_frame_id="laser",
                            transform=Transform(translation=Vector3(x=x, y=y, z=0.3), rotation=q))


POSES = [(-2.0 + 0.2 * i, -1.0 + 0.1 * (i % 5), 0.05 * i) for i in range(25)]


# ---------------------------------------------------------------- a real service in this process


@dataclass
class LiveService:
    """The service (``create_app``) served by uvicorn on a loopback port, in a thread."""

    url: str
    app: Any

    @property
    def service(self) -> Any:
        return self.app.state.service


@pytest.fixture
def serve(tmp_path: Any) -> Iterator[Callable[..., LiveService]]:
    started: list[tuple[uvicorn.Server, threading.Thread]] = []

    def start(**overrides: Any) -> LiveService:
        settings = Settings(data_dir=tmp_path / f"data{len(started)}", plan_warmup=False, plan_workers=1, **overrides)
        app = create_app(settings)
        sock = bind("127.0.0.1", 0)
        server = uvicorn.Server(uvicorn.Config(app, log_config=None, access_log=False))
        thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="test-uvicorn")
        thread.start()
        started.append((server, thread))
        url = f"http://127.0.0.1:{sock.getsockname()[1]}"
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            try:
                if server.started and httpx.get(f"{url}/ready", timeout=5).status_code == 200:
                    return LiveService(url, app)
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        raise AssertionError("the service did not become ready")

    yield start
    for server, thread in started:
        server.should_exit = True
        thread.join(60)
        assert not thread.is_alive()


# ---------------------------------------------------------------- a scripted HTTP server


@dataclass
class Reply:
    status: int = 200
    headers: dict[str, str] = field(default_factory=dict)
    stall_s: float = 0.0  # wait this long before answering (a service that does not answer in time)
    body: str | None = None  # the answer's body as it is (default: the service's JSON)


class Scripted:
    """Answers each POST with the next ``Reply`` (the last one repeats); records when and what came."""

    def __init__(self, replies: list[Reply]) -> None:
        self.replies = replies
        self.requests: list[tuple[float, dict[str, Any]]] = []
        self.release = threading.Event()  # ends any stall at teardown
        script = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                index = len(script.requests)
                script.requests.append((time.monotonic(), body))
                reply = script.replies[min(index, len(script.replies) - 1)]
                if reply.stall_s:
                    script.release.wait(reply.stall_s)
                payload = (reply.body if reply.body is not None else json.dumps(
                    {"version": index + 1} if reply.status == 200  # else the service's ErrorBody
                    else {"code": "INVALID", "message": f"no ({reply.status})", "details": None}))
                try:
                    self.send_response(reply.status)
                    for key, value in {"Content-Type": "application/json", **reply.headers}.items():
                        self.send_header(key, value)
                    self.end_headers()
                    self.wfile.write(payload.encode())
                except OSError:
                    pass  # the client gave up waiting (the timeout case)

            def log_message(self, *args: object) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.block_on_close = True  # server_close joins the handler threads
        self.thread = threading.Thread(target=self.server.serve_forever, name="test-scripted-http")
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"

    def close(self) -> None:
        self.release.set()
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(10)
        assert not self.thread.is_alive()


@pytest.fixture
def scripted() -> Iterator[Callable[[list[Reply]], Scripted]]:
    servers: list[Scripted] = []

    def make(replies: list[Reply]) -> Scripted:
        servers.append(Scripted(replies))
        return servers[-1]

    yield make
    for server in servers:
        server.close()


@pytest.fixture
def bridges() -> Iterator[Callable[..., Bridge]]:
    """Bridges made by a test; each is closed, and its worker thread must have ended."""
    made: list[Bridge] = []

    def make(url: str, **options: Any) -> Bridge:
        made.append(Bridge(BridgeConfig(url=url, map_name="lab", **options)))
        return made[-1]

    yield make
    for bridge in made:
        bridge.close(timeout_s=2.0)
        assert bridge._thread is None or not bridge._thread.is_alive()


def wait_for(condition: Callable[[], bool], timeout_s: float = 30.0) -> float:
    """Poll until ``condition()``; the time.monotonic() at which it held."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)
    return time.monotonic()


# ---------------------------------------------------------------- conversion


def test_scan_to_json_takes_the_pose_from_tf_and_keeps_rep117_readings() -> None:
    ranges = np.array([1.5, np.inf, -np.inf, np.nan, 2.25], dtype=np.float32)
    scan = scan_to_json(laser_msg(stamp_s=12.5, ranges=ranges), tf_msg(1.0, -2.0, 0.7))
    assert scan["header"] == {"stamp": {"sec": 12, "nanosec": 500_000_000}}  # the message's, kept by the service
    assert scan["pose"] == {"x": 1.0, "y": -2.0, "theta": pytest.approx(0.7, abs=1e-12)}
    assert scan["ranges"] == [1.5, "inf", "-inf", None, 2.25]
    assert scan["angle_min"] == pytest.approx(-math.pi / 4) and scan["angle_increment"] > 0
    assert (scan["range_min"], scan["range_max"]) == (0.1, 20.0)
    # float32 readings go out as the exact float64 of their float32 (what a binary upload carries)
    odd = scan_to_json(laser_msg(ranges=np.array([3.1], dtype=np.float32)), tf_msg(0, 0, 0))
    assert odd["ranges"] == [float(np.float32(3.1))]


def test_a_scan_whose_stamp_is_not_ros_time_is_skipped_not_sent() -> None:
    msg = laser_msg()
    msg.header.stamp.sec = -1
    with pytest.raises(ValueError, match="header.stamp"):
        scan_to_json(msg, tf_msg(0, 0, 0))


def test_scan_to_json_turns_an_upside_down_laser_the_other_way() -> None:
    scan = scan_to_json(laser_msg(), tf_msg(0.0, 0.0, 0.5, roll=math.pi))
    assert scan["pose"]["theta"] == pytest.approx(0.5)
    assert scan["angle_min"] == pytest.approx(math.pi / 4)  # the sweep mirrored: first beam on the right
    assert scan["angle_increment"] < 0


def quaternion(roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> tuple[float, float, float, float]:
    """(x, y, z, w) of yaw about z, then pitch about y, then roll about x (ZYX, as tf2's setRPY)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def orientations() -> list[tuple[str, tuple[float, float, float, float]]]:
    """Level, upside down, tilted by 1, 2.9, 3.1 and 10 degrees (about x, y and a diagonal), non-normalised."""
    cases: list[tuple[str, tuple[float, float, float, float]]] = []
    for yaw in (0.0, 0.7, -2.5, math.pi):
        cases.append((f"level yaw {yaw}", quaternion(yaw=yaw)))
        cases.append((f"upside down yaw {yaw}", quaternion(roll=math.pi, yaw=yaw)))
        cases.append((f"upside down by pitch yaw {yaw}", quaternion(pitch=math.pi, yaw=yaw)))
        for degrees in (1.0, 2.9, 3.1, 10.0):
            tilt = math.radians(degrees)
            for flip in (0.0, math.pi):
                cases.append((f"roll {degrees} flip {flip} yaw {yaw}", quaternion(roll=flip + tilt, yaw=yaw)))
                cases.append((f"pitch {degrees} flip {flip} yaw {yaw}", quaternion(roll=flip, pitch=tilt, yaw=yaw)))
                diagonal = tilt / math.sqrt(2)
                cases.append((f"diagonal {degrees} flip {flip} yaw {yaw}",
                              quaternion(roll=flip + diagonal, pitch=diagonal, yaw=yaw)))
    scaled = []
    for label, q in cases[:: 3]:
        for scale in (0.5, 1.001, 7.0):  # a tf2 quaternion off unit length, or any multiple of one
            scaled.append((f"{label} x{scale}", tuple(scale * c for c in q)))
    return cases + scaled


def test_the_bridge_places_a_scan_as_the_service_places_a_cdr_body() -> None:
    """The bridge's copy of the level rule (``core.level_heading``) against the service's (``app.ros.messages_in``)."""
    refused = accepted = 0
    for label, q in orientations():
        try:
            theta, turn = level_heading(SensorPose((0.0, 0.0, 0.0), q), "scan")
        except Invalid as exc:  # the service refuses it: the bridge must too
            assert "tilted" in str(exc), label
            with pytest.raises(NotLevel):
                scan_to_json(laser_msg(), tf_quaternion(q))
            refused += 1
            continue
        scan = scan_to_json(laser_msg(), tf_quaternion(q))
        assert scan["pose"]["theta"] == pytest.approx(theta, abs=1e-12), label
        assert scan["angle_min"] == turn * laser_msg().angle_min, label
        assert scan["angle_increment"] == turn * laser_msg().angle_increment, label
        accepted += 1
    assert refused and accepted  # both sides of the rule were met


def test_a_tilted_laser_is_refused_counted_and_said_why(
    bridges: Callable[..., Bridge], caplog: pytest.LogCaptureFixture,
) -> None:
    bridge = bridges("http://127.0.0.1:9")  # never started: nothing is sent
    caplog.set_level(logging.WARNING, logger="fuzzyrisk_bridge")
    bridge.submit(laser_msg(), tf_quaternion(quaternion(pitch=math.radians(10.0))))
    bridge.submit(laser_msg(), tf_quaternion(quaternion(roll=math.radians(2.0))))  # within 3 degrees: taken
    assert (bridge.stats.received, bridge.stats.skipped, bridge.stats.tilted, bridge.stats.queued) == (2, 1, 1, 1)
    assert any("scan skipped: the laser is tilted 10.0 degrees from level" in r.getMessage() for r in caplog.records)


def tf_quaternion(q: tuple[float, float, float, float]) -> Any:
    """``T_map_laser`` with the rotation ``q`` (x, y, z, w) as it is, not normalised."""
    rotation = Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])
    return TransformStamped(header=Header(stamp=Time(sec=0, nanosec=0), frame_id="map"), child_frame_id="laser",
                            transform=Transform(translation=Vector3(x=1.0, y=2.0, z=0.3), rotation=rotation))


# ---------------------------------------------------------------- against the real service


def test_scans_are_posted_in_batches_and_fuse_as_the_same_scans_posted_directly(
    serve: Callable[..., LiveService], bridges: Callable[..., Bridge],
) -> None:
    live = serve()
    with httpx.Client(base_url=live.url, timeout=30) as http:
        for name in ("lab", "direct"):
            assert http.post("/maps", json={**MAP, "name": name}).status_code == 201
        # every scan is queued before the worker starts: two full batches leave at once, the last 5 scans after
        # max_delay_s (the default 0.5 s; the batches are the same at any delay)
        bridge = bridges(live.url, batch_size=10, max_delay_s=0.5)
        for i, (x, y, yaw) in enumerate(POSES):
            bridge.on_scan(laser_msg(stamp_s=0.1 * i), lambda frame, stamp, p=(x, y, yaw): tf_msg(*p))
        assert bridge.pending == 25  # not started yet: nothing sent
        bridge.start()
        wait_for(lambda: bridge.stats.scans_posted == 25)
        info = http.get("/maps/lab").json()
        assert (info["scans_fused"], info["version"]) == (25, 3)  # 10 + 10 + 5: three POSTs
        assert bridge.stats.batches_posted == 3 and bridge.stats.version == 3
        # the same scans, built by hand from the poses, posted in the same batches
        for start in (0, 10, 20):
            scans = [{"pose": {"x": x, "y": y, "theta": yaw}, "angle_min": -math.pi / 4,
                      "angle_increment": (math.pi / 2) / (BEAMS - 1), "range_min": 0.1, "range_max": 20.0,
                      "ranges": [float(r) for r in laser_msg().ranges]} for x, y, yaw in POSES[start:start + 10]]
            assert http.post("/maps/direct/scans", json={"scans": scans}).status_code == 200
        bridged = http.get("/maps/lab/risk", params={"format": "npy"}).content
        direct = http.get("/maps/direct/risk", params={"format": "npy"}).content
        # each scan kept its message's stamp, and comes back with the pose tf gave it
        poses = http.get("/maps/lab/trajectory").json()["poses"]
    assert bridged == direct
    sent = [laser_msg(stamp_s=0.1 * i).header.stamp for i in range(len(POSES))]
    assert [p["header"]["stamp"] for p in poses] == [{"sec": t.sec, "nanosec": t.nanosec} for t in sent]
    assert [(p["pose"]["position"]["x"], p["pose"]["position"]["y"]) for p in poses] == [(x, y) for x, y, _ in POSES]
    assert bridge.stats.as_dict() | {"version": None} == {
        "received": 25, "queued": 25, "dropped": 0, "skipped": 0, "tilted": 0, "errors": 0, "scans_posted": 25,
        "batches_posted": 3, "batches_failed": 0, "retries": 0, "throttled": 0, "timeouts": 0, "version": None}


def test_a_503_from_a_full_line_is_retried_after_its_retry_after(
    serve: Callable[..., LiveService], bridges: Callable[..., Bridge], caplog: pytest.LogCaptureFixture,
) -> None:
    """The service's own back-pressure: one batch in line (FUZZYRISK_MAX_PENDING_BATCHES=1) is fusing, so
    the bridge's batch gets 503 with ``Retry-After: 1``; the bridge waits that second (not its 0.05 s
    backoff) and the retry is fused."""
    live = serve(max_pending_batches=1)
    service = live.service
    entered, release = threading.Event(), threading.Event()
    apply = service.writes._apply

    def slow_apply(*args: Any) -> Any:  # the first batch fuses until the test lets it finish
        if not entered.is_set():
            entered.set()
            release.wait(30)
        return apply(*args)

    service.writes._apply = slow_apply
    caplog.set_level(logging.WARNING, logger="fuzzyrisk_bridge")
    with httpx.Client(base_url=live.url, timeout=60) as http:
        assert http.post("/maps", json=MAP).status_code == 201
        first = threading.Thread(target=httpx.post, args=(f"{live.url}/maps/lab/scans",),  # a client of its own
                                 kwargs={"json": {"scans": [scan_to_json(laser_msg(), tf_msg(0, 0, 0))]}, "timeout": 60})
        first.start()
        try:
            assert entered.wait(30)
            bridge = bridges(live.url, backoff_s=0.05, max_backoff_s=5.0, max_delay_s=0.0)
            bridge.submit(laser_msg(), tf_msg(1.0, 0.0, 0.0))
            bridge.start()
            wait_for(lambda: bridge.stats.throttled == 1)
        finally:
            release.set()
            first.join(30)
        wait_for(lambda: bridge.stats.batches_posted == 1)
        acknowledged = time.time()  # wall clock, as LogRecord.created
        refused = next(r for r in caplog.records if r.getMessage().startswith("503 from the service"))
        assert "FUZZYRISK_MAX_PENDING_BATCHES" in refused.getMessage()  # the service's own message, logged
        assert acknowledged - refused.created >= 0.9 - 0.05  # Retry-After: 1 honoured
        assert bridge.stats.retries == 1 and bridge.stats.batches_failed == 0
        assert http.get("/maps/lab").json()["scans_fused"] == 2


# ---------------------------------------------------------------- retries, timeouts, the queue


def test_retry_after_429_backoff_and_the_cap(
    scripted: Callable[[list[Reply]], Scripted], bridges: Callable[..., Bridge],
) -> None:
    server = scripted([Reply(503, {"Retry-After": "1"}), Reply(429), Reply(503, {"Retry-After": "3600"}), Reply(200)])
    bridge = bridges(server.url, backoff_s=0.05, max_backoff_s=1.2, max_delay_s=0.0)
    bridge.submit(laser_msg(), tf_msg(0, 0, 0))
    bridge.start()
    wait_for(lambda: bridge.stats.batches_posted == 1)
    times = [t for t, _ in server.requests]
    gaps = np.diff(times)
    assert len(times) == 4
    assert gaps[0] >= 0.95  # Retry-After: 1
    assert 0.09 <= gaps[1] < 0.35  # a 429 without Retry-After: the backoff of the 2nd attempt, 0.05 * 2
    assert 1.15 <= gaps[2] < 2.0  # Retry-After: 3600 waits the cap, 1.2 s
    assert bridge.stats.throttled == 3 and bridge.stats.retries == 3 and bridge.stats.version == 4


def test_a_timeout_is_retried_and_the_batch_sent_again(
    scripted: Callable[[list[Reply]], Scripted], bridges: Callable[..., Bridge],
) -> None:
    server = scripted([Reply(200, stall_s=3.0), Reply(200)])
    bridge = bridges(server.url, timeout_s=0.3, backoff_s=0.05, max_delay_s=0.0)
    bridge.submit(laser_msg(), tf_msg(0, 0, 0))
    started = time.monotonic()
    bridge.start()
    done = wait_for(lambda: bridge.stats.batches_posted == 1)
    assert done - started < 2.0  # did not wait for the stalled answer
    assert bridge.stats.timeouts == 1 and bridge.stats.retries == 1
    assert server.requests[0][1] == server.requests[1][1]  # at least once: the same batch again


def test_an_answer_that_retrying_cannot_change_drops_the_batch(
    scripted: Callable[[list[Reply]], Scripted], bridges: Callable[..., Bridge], caplog: pytest.LogCaptureFixture,
) -> None:
    server = scripted([Reply(422), Reply(200)])
    bridge = bridges(server.url, max_delay_s=0.0)
    bridge.submit(laser_msg(), tf_msg(0, 0, 0))
    bridge.start()
    wait_for(lambda: bridge.stats.batches_failed == 1)
    bridge.submit(laser_msg(), tf_msg(0, 0, 0))  # the next batch goes on as usual
    wait_for(lambda: bridge.stats.batches_posted == 1)
    assert len(server.requests) == 2 and bridge.stats.retries == 0
    # the service's words: the code and the message of its ErrorBody
    assert any(r.getMessage().endswith(f"422 from {server.url}/maps/lab/scans: INVALID: no (422)") for r in caplog.records)


def test_an_error_body_not_of_the_service_is_logged_as_it_is(
    scripted: Callable[[list[Reply]], Scripted], bridges: Callable[..., Bridge], caplog: pytest.LogCaptureFixture,
) -> None:
    """A proxy's page or a fuzzyrisk older than ``{code, message, details}`` (FastAPI's ``{"detail"}``): its body."""
    server = scripted([Reply(404, body='{"detail": "Not Found"}'), Reply(502, body="<html>Bad Gateway</html>"), Reply(200)])
    bridge = bridges(server.url, backoff_s=0.01, max_delay_s=0.0)
    caplog.set_level(logging.WARNING, logger="fuzzyrisk_bridge")
    bridge.submit(laser_msg(), tf_msg(0, 0, 0))
    bridge.start()
    wait_for(lambda: bridge.stats.batches_failed == 1)
    bridge.submit(laser_msg(), tf_msg(0, 0, 0))
    wait_for(lambda: bridge.stats.batches_posted == 1)
    messages = [r.getMessage() for r in caplog.records]
    assert any(m.endswith('404 from ' + server.url + '/maps/lab/scans: {"detail": "Not Found"}') for m in messages)
    assert any(m.startswith("502 from the service (<html>Bad Gateway</html>)") for m in messages)


def test_the_queue_keeps_the_newest_scans_and_counts_the_dropped(
    scripted: Callable[[list[Reply]], Scripted], bridges: Callable[..., Bridge], caplog: pytest.LogCaptureFixture,
) -> None:
    server = scripted([Reply(200)])
    bridge = bridges(server.url, queue_size=5, batch_size=10, max_delay_s=0.0)
    caplog.set_level(logging.WARNING, logger="fuzzyrisk_bridge")
    for i in range(12):
        bridge.submit(laser_msg(), tf_msg(float(i), 0.0, 0.0))
    assert bridge.pending == 5 and bridge.stats.dropped == 7 and bridge.stats.queued == 12
    full = [r for r in caplog.records if "queue full" in r.getMessage()]
    assert len(full) == 1  # throttled: one line for the burst, not seven
    bridge.start()
    wait_for(lambda: bridge.stats.scans_posted == 5)
    assert [s["pose"]["x"] for s in server.requests[0][1]["scans"]] == [7.0, 8.0, 9.0, 10.0, 11.0]


def test_no_exception_escapes_a_callback(bridges: Callable[..., Bridge], caplog: pytest.LogCaptureFixture) -> None:
    bridge = bridges("http://127.0.0.1:9")  # never started: nothing is sent

    def no_transform(frame: str, stamp: Any) -> Any:
        raise LookupError(f'"map" passed to lookupTransform argument target_frame does not exist ({frame})')

    class Hostile:
        @property
        def header(self) -> Any:
            raise RuntimeError("a bug in a message class")

    bridge.on_scan(laser_msg(), no_transform)  # TF not there yet
    bridge.on_scan(None, lambda frame, stamp: tf_msg(0, 0, 0))  # not a message
    bridge.on_scan(Hostile(), lambda frame, stamp: tf_msg(0, 0, 0))  # raising attribute
    bridge.submit(laser_msg(), None)  # no transform
    bridge.submit(laser_msg(), tf_msg(math.nan, 0, 0))  # a NaN pose
    bridge.submit(object(), tf_msg(0, 0, 0))  # no LaserScan fields
    bridge.submit(laser_msg(ranges=np.array([1.0], dtype=np.float32)), tf_msg(0, 0, 0))  # a good one
    bridge.close(timeout_s=0.1)
    bridge.submit(laser_msg(), tf_msg(0, 0, 0))  # after close: counted, not raised
    assert bridge.stats.received == 8 and bridge.stats.skipped == 6 and bridge.stats.queued == 1
    assert bridge.stats.dropped == 2  # the good one, left at close, and the one after it
    assert any("no transform into the map frame" in r.getMessage() for r in caplog.records)


def test_close_ends_the_worker_while_the_service_is_unreachable(bridges: Callable[..., Bridge]) -> None:
    bridge = bridges("http://127.0.0.1:9", backoff_s=0.2, max_backoff_s=0.2, max_attempts=1000, max_delay_s=0.0)
    bridge.submit(laser_msg(), tf_msg(0, 0, 0))
    bridge.start()
    wait_for(lambda: bridge.stats.retries >= 1)
    started = time.monotonic()
    bridge.close(timeout_s=0.5)
    assert time.monotonic() - started < 2.0
    assert bridge._thread is not None and not bridge._thread.is_alive()
    assert bridge.stats.batches_failed == 1 and bridge.stats.batches_posted == 0


def test_the_node_says_how_to_get_rclpy_when_it_is_missing(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setitem(sys.modules, "rclpy", None)  # import rclpy raises ImportError, as without ROS
    monkeypatch.delitem(sys.modules, "fuzzyrisk_bridge.node", raising=False)
    assert bridge_main.main(["--map", "lab"]) == bridge_main.EXIT_STARTUP_FAILURE
    assert "source /opt/ros/" in capsys.readouterr().err
