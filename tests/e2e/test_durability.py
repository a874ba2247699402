"""kill -9 during a stream of batches: every acknowledged batch is there, and the map is exactly a
fresh in-process fusion of the batches it holds; after a kill -9 the trajectory (stamps and poses) is the same.
SIGTERM: a batch in flight is finished and kept."""

from __future__ import annotations

import io
import math
import random
import threading
import time
from collections.abc import Sequence
from typing import Any, overload

import numpy as np
import pytest

from fuzzyocc import FuzzyMap, GridSpec, LaserScan, SensorModel
from tests.e2e.conftest import PATIENCE_S

pytestmark = pytest.mark.slow


class _Bodies(Sequence[dict[str, Any]]):
    """``count`` batches of one scan each, at poses jittered about the world's: the first ``ahead`` made at once (a
    stream sends them back to back), the others at their first use, then kept. A stream cut by a kill sends a dozen
    of its 80 bodies; at 40,000 beams the other bodies took seconds to make."""

    def __init__(self, world: Any, count: int, beams: int, ahead: int) -> None:
        rng = random.Random(5)
        self._poses = [(x + rng.uniform(-0.3, 0.3), y + rng.uniform(-0.3, 0.3), th + rng.uniform(-1, 1))
                       for x, y, th in (world.POSES * (count // len(world.POSES) + 1))[:count]]
        self._world, self._beams = world, beams
        self._made: dict[int, dict[str, Any]] = {}
        for i in range(min(ahead, count)):
            self[i]  # made now, kept

    def __len__(self) -> int:
        return len(self._poses)

    @overload
    def __getitem__(self, index: int) -> dict[str, Any]: ...

    @overload
    def __getitem__(self, index: slice) -> list[dict[str, Any]]: ...

    def __getitem__(self, index: int | slice) -> dict[str, Any] | list[dict[str, Any]]:
        if isinstance(index, slice):
            return [self[i] for i in range(len(self))[index]]
        i = range(len(self))[index]  # IndexError past the end, as a list's
        if i not in self._made:
            self._made[i] = {"scans": [self._world.laser_json(self._poses[i], beams=self._beams)]}
        return self._made[i]


def _bodies(world: Any, count: int, beams: int = 360) -> _Bodies:
    return _Bodies(world, count, beams, ahead=20)


def _replay(world: Any, bodies: Sequence[dict[str, Any]]) -> bytes:
    """The map the service must hold after exactly these batches, fused here in-process."""
    spec = world.MAP
    fresh = FuzzyMap(GridSpec(origin=spec["origin"], size=spec["size"], resolution=spec["resolution"]),
                     SensorModel(**spec["sensor"]))
    for body in bodies:
        (s,) = body["scans"]
        ranges = np.array([math.inf if r == "inf" else r for r in s["ranges"]], dtype=np.float64)
        fresh.integrate_batch([LaserScan(pose=(s["pose"]["x"], s["pose"]["y"], s["pose"]["theta"]),
                                         angle_min=s["angle_min"], angle_increment=s["angle_increment"],
                                         ranges=ranges, range_min=s["range_min"], range_max=s["range_max"])])
    return np.ascontiguousarray(fresh.risk()).tobytes()


# 360 beams: snapshots mid-stream too; 40,000: each batch's payload (320 kB of float64) is a file beside the
# database, and none is snapshotted over before the kill
@pytest.mark.parametrize(("beams", "snapshot_every"), [(360, "4"), (40_000, "1000")])
def test_kill_9_mid_stream_loses_no_acknowledged_batch(start_server: Any, world: Any, beams: int,
                                                       snapshot_every: str) -> None:
    server = start_server(FUZZYRISK_SNAPSHOT_EVERY=snapshot_every)
    bodies = _bodies(world, 80, beams)
    with server.client() as http:
        assert http.post("/maps", json=world.MAP).status_code == 201
    acked: list[int] = []

    def stream() -> None:
        with server.client(timeout_s=30) as http:
            for body in bodies:
                try:
                    response = http.post("/maps/hall/scans", json=body)
                except Exception:  # the server died under us
                    return
                if response.status_code != 200:
                    return
                acked.append(response.json()["version"])

    sender = threading.Thread(target=stream)
    sender.start()
    deadline = time.monotonic() + PATIENCE_S
    while len(acked) < 10 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(random.Random(11).uniform(0.0, 0.05))  # somewhere inside a request
    server.kill()
    sender.join(timeout=30)
    assert 10 <= len(acked) < len(bodies), "the kill must land mid-stream"
    assert acked == list(range(1, len(acked) + 1))

    files = list((server.data_dir / "fuzzyrisk.sqlite3-payloads").glob("*.bin"))
    assert len(files) >= (len(acked) if beams > 360 else 0), (len(files), len(acked))
    server = start_server()
    with server.client() as http:
        version = http.get("/maps/hall").json()["version"]
        assert acked[-1] <= version <= acked[-1] + 1  # the unanswered batch: wholly there or not at all
        held = http.get("/maps/hall/risk", params={"format": "npy"}).content
    risk = np.load(io.BytesIO(held))
    assert risk.tobytes() == _replay(world, bodies[:version])


def test_after_kill_9_the_trajectory_is_the_same(start_server: Any, world: Any) -> None:
    server = start_server(FUZZYRISK_SNAPSHOT_EVERY="1000")
    bodies = _bodies(world, 6)
    for k, body in enumerate(bodies[:4]):  # four stamped by the robot, two stamped by the service
        body["scans"][0]["header"] = {"stamp": {"sec": 1_700_000_000 + k, "nanosec": 123_456_789}}
    with server.client() as http:
        assert http.post("/maps", json=world.MAP).status_code == 201
        posted_from = time.time_ns()
        for body in bodies:
            assert http.post("/maps/hall/scans", json=body).status_code == 200
        posted_to = time.time_ns()
        before = http.get("/maps/hall/trajectory").json()
    stamps = [p["header"]["stamp"]["sec"] * 10**9 + p["header"]["stamp"]["nanosec"] for p in before["poses"]]
    assert stamps[:4] == [(1_700_000_000 + k) * 10**9 + 123_456_789 for k in range(4)]
    assert posted_from <= stamps[4] <= stamps[5] <= posted_to
    assert [(p["pose"]["position"]["x"], p["pose"]["position"]["y"]) for p in before["poses"]] == [
        (b["scans"][0]["pose"]["x"], b["scans"][0]["pose"]["y"]) for b in bodies]
    server.kill()

    server = start_server()
    with server.client() as http:
        assert http.get("/maps/hall/trajectory").json() == before


def test_sigterm_finishes_the_batch_in_flight(start_server: Any, world: Any) -> None:
    server = start_server()
    with server.client() as http:
        assert http.post("/maps", json=world.MAP).status_code == 201
    big = {"scans": [world.laser_json(p, beams=1440) for p in world.POSES * 2]}
    answers: list[Any] = []

    def send() -> None:
        with server.client() as http:
            answers.append(http.post("/maps/hall/scans", json=big))

    sender = threading.Thread(target=send)
    sender.start()
    with server.client() as http:  # SIGTERM once the batch is in the service's hands (arriving, or in its line)
        deadline = time.monotonic() + PATIENCE_S
        while http.get("/ready").json()["batches_in_line"] == 0:
            assert not answers, "the batch was done before it was seen in line: the test needs a bigger one"
            assert time.monotonic() < deadline, "the batch never reached the service"
            time.sleep(0.01)
    server.terminate()
    sender.join(timeout=60)
    assert answers and answers[0].status_code == 200 and answers[0].json()["version"] == 1
    assert "Application shutdown complete" in server.log()

    server = start_server()
    with server.client() as http:
        assert http.get("/maps/hall").json()["scans_fused"] == len(big["scans"])
