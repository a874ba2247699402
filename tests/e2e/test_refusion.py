"""Re-fusion for real: ``kill -9`` at any point of a correction, and a fleet of two replicas on one PostgreSQL.

After a kill and a restart the map is entirely before the correction (not acknowledged) or entirely after it, never
a mix; an acknowledged correction is completed by the restarted service. On a fleet every replica serves the rebuilt
map once it is done, and the rebuild's work is done once: by the replica that took the PUT, or, when that one is
killed, by the other once its lease has run out.
"""

from __future__ import annotations

import re
import threading
import time
from typing import Any

import httpx
import pytest

from bench._client import ServerProcess
from fuzzyocc.carmen import read_carmen
from tests.app.api.routes.test_refusion import GROWING, drifted, path_of
from tests.conftest import DATA_DIR
from tests.e2e.conftest import PATIENCE_S

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

LOG = read_carmen(DATA_DIR / "carmen" / "csail-corrected.log.gz")
LEASE = {"FUZZYRISK_REBUILD_LEASE_S": "1"}


def _post(http: httpx.Client, name: str, scans: Any, batch: int = 20) -> None:
    from app.cli.import_log import scan_json

    for i in range(0, len(scans), batch):
        response = http.post(f"/maps/{name}/scans", json={"scans": [scan_json(s) for s in scans[i:i + batch]]})
        assert response.status_code == 200, response.text


def _grid(http: httpx.Client, name: str) -> bytes:
    response = http.get(f"/maps/{name}/risk", params={"format": "npy"})
    assert response.status_code == 200, response.text
    return response.content


def _wait_done(http: httpx.Client, name: str, correction: str | None = None) -> dict[str, Any]:
    deadline = time.monotonic() + PATIENCE_S
    while True:
        status = http.get(f"/maps/{name}/rebuild").json()
        if status["state"] == "done" and correction in (None, status["id"]):
            return dict(status)
        assert status["state"] != "failed" and time.monotonic() < deadline, status
        time.sleep(0.05)


def _rebuilds(url: str) -> float:
    text = httpx.get(f"{url}/metrics", timeout=10).text
    return sum(float(v) for v in re.findall(r'^fuzzyrisk_rebuilds_total\{result="done"\} (\S+)$', text, re.M))


@pytest.mark.parametrize("delay_s", [0.0, 0.03, 0.15, 0.6])
def test_kill_9_at_any_point_leaves_the_map_before_or_after_the_correction(start_server: Any,
                                                                           delay_s: float) -> None:
    server = start_server(**LEASE)
    with server.client() as http:
        for name, scans in (("direct", LOG), ("robot", drifted(LOG))):
            assert http.post("/maps", json={**GROWING, "name": name}).status_code == 201
            _post(http, name, scans)
        expected, before = _grid(http, "direct"), _grid(http, "robot")
    acknowledged: list[str] = []

    def put() -> None:
        try:
            with server.client() as http:
                response = http.put("/maps/robot/trajectory", json=path_of(LOG))
            if response.status_code == 202:
                acknowledged.append(response.json()["rebuild"]["id"])
        except httpx.HTTPError:
            pass  # killed before the answer

    sender = threading.Thread(target=put)
    sender.start()
    time.sleep(delay_s)
    server.kill()
    sender.join(timeout=30)

    server = start_server(**LEASE)
    with server.client() as http:
        assert _grid(http, "robot") in (before, expected)  # never a mix
        status = http.get("/maps/robot/rebuild").json()
        if acknowledged:
            assert status["id"] == acknowledged[0] and status["state"] in ("running", "done")
        if status["state"] != "none":  # acknowledged, or stored with its answer lost: completed either way
            _wait_done(http, "robot", status["id"])
            assert _grid(http, "robot") == expected
        else:
            assert _grid(http, "robot") == before


def test_a_fleet_rebuilds_once_and_every_replica_serves_the_rebuilt_map(postgres_server: Any) -> None:
    url = postgres_server.create_database()
    replicas = [ServerProcess(env={"FUZZYRISK_DATABASE_URL": url, **LEASE}) for _ in range(2)]
    try:
        for replica in replicas:
            replica.start()
        a, b = (httpx.Client(base_url=r.url, timeout=60) for r in replicas)
        with a, b:
            for name, scans in (("direct", LOG), ("robot", drifted(LOG))):
                assert a.post("/maps", json={**GROWING, "name": name}).status_code == 201
                _post(a, name, scans)
            expected, before = _grid(a, "direct"), _grid(a, "robot")
            assert _grid(b, "robot") == before  # B holds the map too, before the correction
            response = a.put("/maps/robot/trajectory", json=path_of(LOG))
            assert response.status_code == 202, response.text
            status = _wait_done(b, "robot", response.json()["rebuild"]["id"])  # B reads the status from the store
            assert _grid(b, "robot") == expected and _grid(a, "robot") == expected
            assert b.get("/maps/robot").json()["version"] == status["version"]
            assert (_rebuilds(replicas[0].url), _rebuilds(replicas[1].url)) == (1.0, 0.0)

            # the replica running a rebuild is killed: the other takes it over once its lease runs out
            second = a.put("/maps/robot/trajectory", json=path_of(drifted(LOG, seed=8)))
            assert second.status_code == 202
            replicas[0].kill()
            _wait_done(b, "robot", second.json()["rebuild"]["id"])
            assert _grid(b, "robot") not in (before, expected)
            assert _rebuilds(replicas[1].url) == 1.0
    finally:
        for replica in replicas:
            replica.close()
