"""One live server with an API key and small limits, shared by the hostile-input tests.

The server runs ``python -m app`` on loopback (``bench._client.ServerProcess``) with limits
small enough to be crossed cheaply, once with SQLite and once on PostgreSQL. Every hostile request must get a 4xx and leave every map
as it was: :func:`map_states` reads the version and scan count of every map before and after.
A session summary line reports how many hostile requests were sent.
"""

from __future__ import annotations

import secrets
from collections import Counter
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest

from bench._client import ServerProcess

API_KEY = secrets.token_urlsafe(24)
LIMITS = {
    "FUZZYRISK_MAX_BODY_BYTES": str(256 * 1024),
    "FUZZYRISK_MAX_SCANS_PER_BATCH": "8",
    "FUZZYRISK_MAX_RAYS_PER_SCAN": "4096",
    "FUZZYRISK_MAX_MAP_CELLS": "200000",
    "FUZZYRISK_MAX_QUERY_POINTS": "1000",
    "FUZZYRISK_MAX_PLAN_TIME_S": "0.3",
    "FUZZYRISK_PLAN_WORKERS": "1",
    "FUZZYRISK_PLAN_QUEUE": "2",
}
MAX_BODY = 256 * 1024
MAX_RAYS = 4096
MAX_SCANS = 8
MAX_QUERY_POINTS = 1000

# maps the hand-written cases aim at (the schema-driven test keeps its own)
FLAT = {"name": "h-flat", "dimensions": 2, "resolution": 0.1, "origin": [-2.0, -2.0], "size": [4.0, 4.0],
        "model": "fuzzy", "sensor": {"range_sigma": 0.03}}
CUBE = {"name": "h-cube", "dimensions": 3, "resolution": 0.2, "origin": [-2.0, -2.0, 0.0], "size": [4.0, 4.0, 2.0],
        "model": "fuzzy", "sensor": {"range_sigma": 0.03}}
BAYES = {**FLAT, "name": "h-bayes", "model": "bayes"}

#: hostile requests sent, by kind, and the statuses of the schema-generated ones (reported at the end)
SENT: Counter[str] = Counter()
STATUSES: Counter[int] = Counter()


def laser(beams: int = 90, **overrides: Any) -> dict[str, Any]:
    """A valid LaserScan facing a wall 1.5 m ahead from the map centre."""
    angle_min, inc = -np.pi / 4, (np.pi / 2) / (beams - 1)
    ranges = (1.5 / np.cos(angle_min + inc * np.arange(beams))).round(4).tolist()
    scan: dict[str, Any] = {"pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": angle_min,
                            "angle_increment": inc, "ranges": ranges, "range_min": 0.05, "range_max": 10.0}
    scan.update(overrides)
    return scan


def cloud(**overrides: Any) -> dict[str, Any]:
    """A valid point cloud (sensor frame) for the 3-D map."""
    points = [[1.5, y, z] for y in (-0.5, 0.0, 0.5) for z in (-0.3, 0.0, 0.3)]
    scan: dict[str, Any] = {"pose": {"position": [0.0, 0.0, 1.0], "orientation": [0.0, 0.0, 0.0, 1.0]},
                            "points": points, "range_max": 10.0}
    scan.update(overrides)
    return scan


@pytest.fixture(scope="session", params=["sqlite", "postgres"])
def hostile_server(request: pytest.FixtureRequest) -> Iterator[ServerProcess]:
    """The server, once on each store: SQLite in its data directory, then PostgreSQL (a fleet's replica)."""
    env = {"FUZZYRISK_API_KEY": API_KEY, **LIMITS}
    if request.param == "postgres":
        env["FUZZYRISK_DATABASE_URL"] = request.getfixturevalue("postgres_server").create_database()
    server = ServerProcess(env=env)
    server.start()
    try:
        with httpx.Client(base_url=server.url, headers=auth(), timeout=60.0) as client:
            for body, scan in ((FLAT, laser()), (BAYES, laser()), (CUBE, cloud())):
                client.post("/maps", json=body).raise_for_status()
                client.post(f"/maps/{body['name']}/scans", json={"scans": [scan]}).raise_for_status()
        yield server
    finally:
        server.close()


def auth(key: str = API_KEY) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


@pytest.fixture
def client(hostile_server: ServerProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=hostile_server.url, headers=auth(), timeout=60.0) as c:
        yield c


def map_states(client: httpx.Client) -> dict[str, tuple[int, int]]:
    """name -> (version, scans_fused) of every map the server holds."""
    response = client.get("/maps")
    assert response.status_code == 200, response.text
    return {m["name"]: (m["version"], m["scans_fused"]) for m in response.json()}


def assert_refused(response: httpx.Response, allowed: set[int] | frozenset[int]) -> None:
    """A 4xx from ``allowed`` with the service's error body: a code and a message a person can read."""
    assert response.status_code in allowed, f"{response.status_code} {response.text[:300]}"
    assert 400 <= response.status_code < 500
    assert_error_body(response)


def assert_error_body(response: httpx.Response) -> None:
    """The one error body: ``{code, message, details}``, code in upper snake case, message not empty."""
    body = response.json()
    assert isinstance(body, dict) and set(body) == {"code", "message", "details"}, body
    assert isinstance(body["code"], str) and body["code"].replace("_", "").isupper(), body
    assert isinstance(body["message"], str) and body["message"], body


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if SENT:
        parts = ", ".join(f"{n} {k}" for k, n in sorted(SENT.items()))
        terminalreporter.write_line(f"hostile requests sent: {sum(SENT.values())} ({parts})")
    if STATUSES:
        parts = ", ".join(f"{status}: {n}" for status, n in sorted(STATUSES.items()))
        terminalreporter.write_line(f"schema-generated requests by status: {parts}")
