"""The Foxglove live view (app/foxglove_live.py), seen by a client of the Foxglove WebSocket protocol.

The client is written here from the protocol: it offers the subprotocols ``foxglove.websocket.v1``
and ``foxglove.sdk.v1`` (foxglove-sdk 0.30's server accepts only the second, its name for the same
protocol, and refuses a client offering only the first), reads
``serverInfo`` and ``advertise``, sends ``subscribe``, and decodes binary message frames (opcode
0x01, uint32 subscription id, uint64 timestamp, payload) whose payload is protobuf, decoded by the
small wire-format reader below (no generated code). The service is ``python -m app`` with
``FUZZYRISK_FOXGLOVE_PORT`` set.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import struct
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from websockets.sync.client import ClientConnection, connect

from tests.e2e.conftest import PATIENCE_S, ROOT, Server, World, free_port

pytestmark = pytest.mark.slow

SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
MESSAGE_DATA = 0x01


# ---------------------------------------------------------------- protobuf, just enough to read a message


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, pos


def protobuf_fields(data: bytes) -> dict[int, list[Any]]:
    """A message's fields by number: varints as int, fixed32/64 as raw bytes, length-delimited as bytes."""
    fields: dict[int, list[Any]] = {}
    pos = 0
    while pos < len(data):
        key, pos = _varint(data, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(data, pos)
        elif wire == 1:
            value, pos = data[pos:pos + 8], pos + 8
        elif wire == 2:
            length, pos = _varint(data, pos)
            value, pos = data[pos:pos + length], pos + length
        elif wire == 5:
            value, pos = data[pos:pos + 4], pos + 4
        else:
            raise AssertionError(f"wire type {wire} is not used by Foxglove's schemas")
        fields.setdefault(number, []).append(value)
    return fields


def decode_grid(payload: bytes) -> dict[str, Any]:
    """foxglove.Grid (foxglove/Grid.proto: 2 frame_id, 3 pose, 4 column_count, 5 cell_size, 6 row_stride,
    7 cell_stride, 8 fields, 9 data)."""
    f = protobuf_fields(payload)
    position = protobuf_fields(protobuf_fields(f[3][0])[1][0])  # pose.position: x 1, y 2 (doubles)
    cell_size = protobuf_fields(f[5][0])
    fields = {}
    for raw in f[8]:
        field = protobuf_fields(raw)
        offset = struct.unpack("<I", field[2][0])[0] if 2 in field else 0
        fields[field[1][0].decode()] = (offset, field.get(3, [0])[0])
    return {
        "frame_id": f[2][0].decode(),
        "origin": [struct.unpack("<d", position.get(k, [bytes(8)])[0])[0] for k in (1, 2)],
        "column_count": struct.unpack("<I", f[4][0])[0],
        "cell_size": struct.unpack("<d", cell_size[1][0])[0],
        "row_stride": struct.unpack("<I", f[6][0])[0],
        "cell_stride": struct.unpack("<I", f[7][0])[0],
        "fields": fields,
        "data": f[9][0],
    }


# ---------------------------------------------------------------- a Foxglove WebSocket client


class FoxgloveClient:
    """The client side of the Foxglove WebSocket protocol, as much as a viewer needs."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        assert self.ws.subprotocol in SUBPROTOCOLS
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[str, dict[str, Any]] = {}  # by topic
        self._subscriptions: dict[int, str] = {}  # subscription id -> topic

    def _handle_text(self, message: dict[str, Any]) -> None:
        if message["op"] == "serverInfo":
            self.server_info = message
        elif message["op"] == "advertise":
            for channel in message["channels"]:
                self.channels[channel["topic"]] = channel
        elif message["op"] == "unadvertise":
            gone = set(message["channelIds"])
            self.channels = {t: c for t, c in self.channels.items() if c["id"] not in gone}

    def wait_for_channel(self, topic: str) -> dict[str, Any]:
        self.receive_until(lambda: topic in self.channels)
        return self.channels[topic]

    def receive_until(self, done: Callable[[], bool]) -> None:
        """Read what the server sends until ``done()`` holds."""
        deadline = time.monotonic() + PATIENCE_S
        while not done():
            self._receive_one(deadline)

    def subscribe(self, topic: str) -> int:
        subscription = len(self._subscriptions) + 1
        channel = self.wait_for_channel(topic)
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": subscription, "channelId": channel["id"]}]}))
        self._subscriptions[subscription] = topic
        return subscription

    def next_message(self, topic: str, wanted: Callable[[bytes], bool] = lambda _: True) -> tuple[int, bytes]:
        """The next message on ``topic`` (subscribed) whose payload is ``wanted``: its timestamp (ns) and payload."""
        deadline = time.monotonic() + PATIENCE_S
        while True:
            frame = self._receive_one(deadline)
            if frame is not None and self._subscriptions.get(frame[0]) == topic and wanted(frame[2]):
                return frame[1], frame[2]

    def _receive_one(self, deadline: float) -> tuple[int, int, bytes] | None:
        left = deadline - time.monotonic()
        assert left > 0, f"what the test waits for did not come in {PATIENCE_S:.0f} s"
        raw = self.ws.recv(timeout=left)
        if isinstance(raw, str):
            self._handle_text(json.loads(raw))
            return None
        assert raw[0] == MESSAGE_DATA, f"unexpected binary opcode {raw[0]:#x}"
        subscription, timestamp = struct.unpack_from("<IQ", raw, 1)
        return subscription, timestamp, raw[13:]


@contextlib.contextmanager
def serve_foxglove(start_server: Callable[..., Server], **env: str) -> Iterator[tuple[Server, Callable[[], FoxgloveClient]]]:
    """``python -m app`` with the live view on (and ``env``), ready with its planner worker up and warmed (the
    tests plan: a first plan that compiles the worker's kernels would take more than its deadline on a busy machine),
    and a maker of viewers connected to it."""
    port = free_port()
    server = start_server(FUZZYRISK_FOXGLOVE_PORT=str(port), FUZZYRISK_FOXGLOVE_INTERVAL_S="0.2",
                          FUZZYRISK_PLAN_WARMUP="true", **env)
    with contextlib.ExitStack() as connections:

        def client() -> FoxgloveClient:
            ws = connections.enter_context(connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS,
                                                   max_size=None, open_timeout=PATIENCE_S, proxy=None))
            return FoxgloveClient(ws)

        yield server, client
    server.terminate()  # SIGTERM: every process it started must end (checked there)
    # the lifespan ran to its end: the view's thread joined and its server stopped, then the maps' shutdown
    assert "Application shutdown complete" in server.log()


@pytest.fixture
def foxglove(start_server: Callable[..., Server]) -> Iterator[tuple[Server, Callable[[], FoxgloveClient]]]:
    with serve_foxglove(start_server) as served:
        yield served


def risk_and_observed(http: Any, name: str) -> tuple[np.ndarray, np.ndarray]:
    layers = []
    for layer in ("risk", "observed"):
        answer = http.get(f"/maps/{name}/risk", params={"format": "npy", "layer": layer})
        assert answer.status_code == 200, answer.text
        layers.append(np.load(io.BytesIO(answer.content), allow_pickle=False))
    return layers[0], layers[1]


def grid_layers(grid: dict[str, Any], shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The grid's float32 ``risk`` field and its rgb, back in the map's (nx, ny) order."""
    nx, ny = shape
    assert grid["column_count"] == nx and grid["row_stride"] == grid["cell_stride"] * nx
    cells = np.frombuffer(grid["data"], dtype=np.uint8).reshape(ny, nx, grid["cell_stride"])
    offset, kind = grid["fields"]["risk"]
    assert kind == 7  # FLOAT32
    risk = cells[:, :, offset:offset + 4].copy().view("<f4")[:, :, 0].T
    rgb = np.stack([cells[:, :, grid["fields"][c][0]] for c in ("red", "green", "blue")], axis=-1).transpose(1, 0, 2)
    return risk, rgb


def test_a_foxglove_client_receives_the_maps_grid(
    foxglove: tuple[Server, Callable[[], FoxgloveClient]], world: type[World],
) -> None:
    server, new_client = foxglove
    with server.client() as http:
        assert http.post("/maps", json=world.MAP).status_code == 201
        scans = [world.laser_json(pose) for pose in world.POSES[:6]]
        assert http.post("/maps/hall/scans", json={"scans": scans}).status_code == 200
        viewer = new_client()
        channel = viewer.wait_for_channel("/fuzzyrisk/hall/grid")
        assert (channel["schemaName"], channel["encoding"]) == ("foxglove.Grid", "protobuf")
        assert viewer.server_info is not None and viewer.server_info["name"] == "fuzzyrisk"

        # a new subscriber gets the current grid at once: the map as GET /risk gives it, bit for bit
        viewer.subscribe("/fuzzyrisk/hall/grid")
        _, payload = viewer.next_message("/fuzzyrisk/hall/grid")
        grid = decode_grid(payload)
        risk, observed = risk_and_observed(http, "hall")
        received, rgb = grid_layers(grid, risk.shape)
        assert received.dtype == np.float32 and np.array_equal(received, risk)
        assert grid["frame_id"] == "map" and grid["origin"] == world.MAP["origin"]
        assert grid["cell_size"] == world.MAP["resolution"]
        assert (rgb[~observed] == (138, 154, 181)).all()  # never observed: the page's grey-blue
        assert (rgb[observed & (risk < 0.05)] > 240).all()  # free: near white

        # the map changes: the view follows with a grid of the new map (those published before may come first)
        version = http.post("/maps/hall/scans", json={"scans": [world.laser_json(world.POSES[-1])]}).json()["version"]
        risk, _ = risk_and_observed(http, "hall")
        assert http.get("/maps/hall").json()["version"] == version
        assert not np.array_equal(received, risk)  # the batch changed the map: the wait below is for the new grid
        viewer.next_message("/fuzzyrisk/hall/grid",
                            lambda payload: np.array_equal(grid_layers(decode_grid(payload), risk.shape)[0], risk))

        # the last scan and a plan have channels too
        scan_channel = viewer.wait_for_channel("/fuzzyrisk/hall/scan")
        assert scan_channel["schemaName"] == "foxglove.LaserScan"
        viewer.subscribe("/fuzzyrisk/hall/scan")
        laser = protobuf_fields(viewer.next_message("/fuzzyrisk/hall/scan")[1])
        assert len(laser[6][0]) == 8 * len(world.laser_json(world.POSES[-1])["ranges"])  # ranges: packed doubles
        plan = http.post("/maps/hall/plan", json={"start": [1.5, 3.0], "goal": [8.5, 3.0], "planner": "grid"})
        assert plan.status_code == 200, plan.text
        assert viewer.wait_for_channel("/fuzzyrisk/hall/plan")["schemaName"] == "foxglove.SceneUpdate"
        viewer.subscribe("/fuzzyrisk/hall/plan")
        update = protobuf_fields(viewer.next_message("/fuzzyrisk/hall/plan")[1])
        line = protobuf_fields(protobuf_fields(update[2][0])[11][0])  # entities[0].lines[0]
        assert len(line[5]) == len(plan.json()["path"])  # one point per path state

        # a deleted map's channels are withdrawn
        assert http.delete("/maps/hall").status_code == 204
        viewer.receive_until(lambda: "/fuzzyrisk/hall/grid" not in viewer.channels)


def test_every_message_of_a_map_is_in_its_frame_and_a_large_grid_goes_in_max_blocks(
    start_server: Callable[..., Server], world: type[World],
) -> None:
    """A map in ``robot1/map``: its scan and plan carry that frame while nobody watches its grid (the grid
    is never read then), and so does its grid. 24,000 cells over FUZZYRISK_FOXGLOVE_MAX_CELLS=10000: the
    grid goes in 2 x 2 blocks, each the largest risk of its observed cells, at twice the resolution."""
    with serve_foxglove(start_server, FUZZYRISK_FOXGLOVE_MAX_CELLS="10000") as (server, new_client):
        with server.client() as http:
            made = http.post("/maps", json={**world.MAP, "name": "r1", "frame_id": "robot1/map"})
            assert made.status_code == 201, made.text
            scans = [world.laser_json(pose) for pose in world.POSES[:6]]
            assert http.post("/maps/r1/scans", json={"scans": scans}).status_code == 200
            plan = http.post("/maps/r1/plan", json={"start": [1.5, 3.0], "goal": [8.5, 3.0], "planner": "grid"})
            assert plan.status_code == 200, plan.text
            viewer = new_client()

            viewer.subscribe("/fuzzyrisk/r1/scan")  # foxglove.LaserScan: 2 frame_id
            assert protobuf_fields(viewer.next_message("/fuzzyrisk/r1/scan")[1])[2][0] == b"robot1/map"
            viewer.subscribe("/fuzzyrisk/r1/plan")  # foxglove.SceneUpdate: 2 entities; SceneEntity: 2 frame_id
            update = protobuf_fields(viewer.next_message("/fuzzyrisk/r1/plan")[1])
            assert protobuf_fields(update[2][0])[2][0] == b"robot1/map"

            viewer.subscribe("/fuzzyrisk/r1/grid")
            grid = decode_grid(viewer.next_message("/fuzzyrisk/r1/grid")[1])
            risk, observed = risk_and_observed(http, "r1")
        assert grid["frame_id"] == "robot1/map" and grid["origin"] == world.MAP["origin"]
        assert risk.shape == (200, 120) and grid["cell_size"] == 2 * world.MAP["resolution"]
        received, _ = grid_layers(grid, (100, 60))
        blocks = np.where(observed, risk, -1.0).reshape(100, 2, 60, 2).max(axis=(1, 3))
        expected = np.where(blocks >= 0, blocks, 0.5).astype(np.float32)
        assert np.array_equal(received, expected)
        assert received.max() == risk[observed].max()  # the walls are all there


def service_env() -> dict[str, str]:
    """This environment without FUZZYRISK_* settings (a run may have some set)."""
    return {k: v for k, v in os.environ.items() if not k.startswith("FUZZYRISK_") or k == "FUZZYRISK_TEST_SESSION"}


def test_the_view_is_off_by_default_and_its_sdk_not_imported() -> None:
    code = ("import sys; from app.api.factory import create_app; from app.config import Settings; "
            "assert Settings().foxglove_port is None; create_app(Settings()); print('foxglove' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], check=False, cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env=service_env())
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_an_sdk_that_fails_to_import_stops_the_start_in_the_same_words(tmp_path: Any) -> None:
    """An SDK that is there but fails to import (a broken install) passes the start's check of the extras
    (``tests/app/ops/test_process_setup.py``: one not installed stops the start before anything); the live view's
    import then stops the start, saying what to do."""
    blocker = tmp_path / "site"  # on PYTHONPATH, so ahead of site-packages: shadows the SDK
    blocker.mkdir()
    (blocker / "foxglove.py").write_text("raise ImportError('No module named foxglove')\n")
    out = subprocess.run(
        [sys.executable, "-m", "app", "--port", str(free_port()), "--data-dir", str(tmp_path / "data")],
        check=False, cwd=ROOT, capture_output=True, text=True, timeout=120,
        env={**service_env(), "PYTHONPATH": str(blocker), "FUZZYRISK_FOXGLOVE_PORT": str(free_port())},
    )
    assert out.returncode != 0  # uvicorn's own status for a failed lifespan (3)
    assert "FUZZYRISK_FOXGLOVE_PORT needs the Foxglove SDK (No module named foxglove)" in out.stderr
    assert "pip install 'fuzzyrisk[foxglove]'" in out.stderr
