"""Fixtures of the service tests: an app on a tmp_path data directory, and small request factories."""

from __future__ import annotations

import io
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.config import Settings
from app.api.factory import create_app
from app.service import mapservice

MAP_2D: dict[str, Any] = {
    "name": "lab", "dimensions": 2, "resolution": 0.1, "origin": [-5.0, -5.0], "size": [10.0, 10.0],
    "model": "fuzzy", "sensor": {"range_sigma": 0.03, "registration_sigma": 0.0},
}
MAP_3D: dict[str, Any] = {
    "name": "hall", "dimensions": 3, "resolution": 0.2, "origin": [-4.0, -4.0, 0.0], "size": [8.0, 8.0, 3.0],
    "model": "fuzzy", "sensor": {"range_sigma": 0.05, "registration_sigma": 0.0},
}


def laser(*, x: float = 0.0, y: float = 0.0, theta: float = 0.0, wall: float = 3.0, beams: int = 90,
          ranges: list[Any] | None = None, **extra: Any) -> dict[str, Any]:
    """A LaserScan facing a straight wall at x = x + wall (in the sensor frame), +-45 degrees."""
    angle_min, increment = -np.pi / 4, (np.pi / 2) / (beams - 1)
    if ranges is None:
        angles = angle_min + increment * np.arange(beams)
        ranges = (wall / np.cos(angles)).round(6).tolist()
    scan = {"pose": {"x": x, "y": y, "theta": theta}, "angle_min": angle_min, "angle_increment": increment,
            "ranges": ranges, "range_min": 0.1, "range_max": 20.0}
    scan.update(extra)
    return scan


def cloud_sensor_points(n: int = 200, distance: float = 2.5) -> np.ndarray:
    """(n, 3) sensor-frame points on a wall ``distance`` ahead (x forward), spread in y and z."""
    rng = np.random.default_rng(7)
    return np.column_stack([np.full(n, distance), rng.uniform(-1.5, 1.5, n), rng.uniform(-0.8, 0.8, n)])


def npy(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.save(out, array)
    return out.getvalue()


@pytest.fixture
def make_settings(tmp_path: Path) -> Callable[..., Settings]:
    """Settings on this test's data directory; no planner processes unless a test plans."""

    def make(**overrides: Any) -> Settings:
        # a small disk reserve: the service's 16 MiB, written by every test's service, came to 15 GB of /tmp
        values: dict[str, Any] = {"data_dir": tmp_path / "data", "plan_warmup": False, "plan_workers": 1,
                                  "disk_reserve_bytes": 64 * 1024}
        values.update(overrides)
        return Settings(**values)

    return make


#: What a service started in this process asks of the collector: nothing. Once ready, a service collects the whole
#: process and freezes what is left (``MapService``); here that is the whole test session, walked again at every
#: app's start (0.1 s or more, hundreds of times). A service's own process does it once: the real server processes
#: of the e2e tests do, and ``test_process_setup``'s test of it puts the real ``gc`` back.
_NO_PROCESS_COLLECTION = SimpleNamespace(collect=lambda *args: 0, freeze=lambda: None, unfreeze=lambda: None)


@pytest.fixture(autouse=True)
def _services_leave_the_collector_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mapservice, "gc", _NO_PROCESS_COLLECTION)


@pytest.fixture
def make_client(make_settings: Callable[..., Settings]) -> Iterator[Callable[..., TestClient]]:
    """Start apps (lifespan included) on the test's data directory; all are stopped at the end."""
    clients: list[TestClient] = []

    def make(**overrides: Any) -> TestClient:
        client = TestClient(create_app(make_settings(**overrides)))
        client.__enter__()
        clients.append(client)
        # as a client of the real service does: wait for /ready, so that the kernels' warm-up (a fusion
        # in a thread of its own) is over before a test counts or patches fusions
        deadline = time.monotonic() + 300
        while client.get("/ready").json()["status"] == "starting" and time.monotonic() < deadline:
            time.sleep(0.02)
        return client

    yield make
    for client in reversed(clients):
        client.__exit__(None, None, None)


@pytest.fixture
def client(make_client: Callable[..., TestClient]) -> TestClient:
    return make_client()


@pytest.fixture
def lab(client: TestClient) -> TestClient:
    """A client whose service holds the 2-D map ``lab`` (10 m x 10 m at 0.1 m, centred on 0)."""
    assert client.post("/maps", json=MAP_2D).status_code == 201
    return client


def risk_npy(client: TestClient, name: str, **headers: str) -> np.ndarray:
    response = client.get(f"/maps/{name}/risk", params={"format": "npy"}, headers=headers)
    assert response.status_code == 200, response.text
    return np.load(io.BytesIO(response.content), allow_pickle=False)


def version(client: TestClient, name: str) -> int:
    return int(client.get(f"/maps/{name}").json()["version"])


def snapshots_stored(client: TestClient, timeout: float = 10.0) -> None:
    """Wait until the snapshots the service copied are stored (a batch is acknowledged before its snapshot is)."""
    writes = client.app.state.service.writes  # type: ignore[attr-defined]
    deadline = time.monotonic() + timeout
    while writes.snapshots_being_written:
        assert time.monotonic() < deadline, "a snapshot was not stored in time"
        time.sleep(0.002)


class Kit:
    """The helpers above, handed to tests as the ``kit`` fixture (test modules cannot import conftest)."""

    MAP_2D = MAP_2D
    MAP_3D = MAP_3D
    laser = staticmethod(laser)
    cloud_sensor_points = staticmethod(cloud_sensor_points)
    npy = staticmethod(npy)
    risk_npy = staticmethod(risk_npy)
    version = staticmethod(version)
    snapshots_stored = staticmethod(snapshots_stored)


@pytest.fixture
def kit() -> type[Kit]:
    return Kit
