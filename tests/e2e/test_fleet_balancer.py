"""The fleet of docs/fleet.md, for real: two replicas on one PostgreSQL behind nginx with ``deploy/fleet/nginx.conf``.

nginx (Debian's package) runs the very configuration the compose file mounts, its two upstream
names pointed at the replicas on loopback. Each map's requests reach one replica (the hash of
its name); when that replica is killed, nginx sends them to the other, which serves the map with
every batch acknowledged before.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

import dev
from bench._client import ServerProcess, free_port

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

CONF = Path(__file__).resolve().parents[2] / "deploy" / "fleet" / "nginx.conf"
MAP = {"dimensions": 2, "resolution": 0.1, "origin": [-5.0, -5.0], "size": [10.0, 10.0], "model": "fuzzy",
       "sensor": {"range_sigma": 0.03}}
NAMES = [f"bay-{k}" for k in range(8)]


def _nginx() -> str:
    found = dev.find_nginx()
    if found is None:
        pytest.fail("nginx is needed: `python3 dev.py test` installs Debian's nginx", pytrace=False)
    return found


def _scan(k: int) -> dict[str, Any]:
    return {"pose": {"x": 0.1 * (k % 5), "y": -0.1 * (k % 3), "theta": 0.2 * k}, "angle_min": -0.8,
            "angle_increment": 0.02, "ranges": [2.0 + 0.01 * k] * 81, "range_min": 0.1, "range_max": 20.0}


@pytest.fixture
def fleet(postgres_server: Any, tmp_path: Path) -> Iterator[tuple[str, list[ServerProcess]]]:
    url = postgres_server.create_database()
    replicas = [ServerProcess(env={"FUZZYRISK_DATABASE_URL": url}) for _ in range(2)]
    nginx: subprocess.Popen[bytes] | None = None
    try:
        for replica in replicas:
            replica.start()
        port = free_port()
        conf = CONF.read_text()
        conf = conf.replace("server replica-a:8000", f"server 127.0.0.1:{replicas[0].port}")
        conf = conf.replace("server replica-b:8000", f"server 127.0.0.1:{replicas[1].port}")
        conf = conf.replace("listen 8000;", f"listen 127.0.0.1:{port};")
        assert str(replicas[0].port) in conf and str(replicas[1].port) in conf, "the upstream lines moved"
        (tmp_path / "nginx.conf").write_text(conf)
        (tmp_path / "logs").mkdir()
        nginx = subprocess.Popen([_nginx(), "-p", str(tmp_path), "-c", str(tmp_path / "nginx.conf"), "-g",
                                  f"daemon off; pid {tmp_path}/nginx.pid; error_log {tmp_path}/logs/error.log;"],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + 30
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert nginx.poll() is None and time.monotonic() < deadline, (tmp_path / "logs" / "error.log").read_text()
            time.sleep(0.1)
        yield f"http://127.0.0.1:{port}", replicas
    finally:
        if nginx is not None:
            os.killpg(nginx.pid, signal.SIGTERM)
            nginx.wait(timeout=30)
        for replica in replicas:
            replica.close()


def _fused(replica: ServerProcess) -> float:
    text = httpx.get(f"{replica.url}/metrics", timeout=10).text
    return sum(float(value) for value in re.findall(r'^fuzzyrisk_scans_fused_total\{[^}]*\} (\S+)$', text, re.M))


def test_each_map_is_fused_on_one_replica_and_served_by_the_other_once_it_is_killed(
        fleet: tuple[str, list[ServerProcess]]) -> None:
    url, replicas = fleet
    with httpx.Client(base_url=url, timeout=60) as client:
        for name in NAMES:
            assert client.post("/maps", json={**MAP, "name": name}).status_code == 201
        for k in range(3):
            for name in NAMES:
                response = client.post(f"/maps/{name}/scans", json={"scans": [_scan(k)]})
                assert response.status_code == 200, response.text
        # map-affine: each map was loaded and fused by one replica only, and both got some
        loaded = [httpx.get(f"{r.url}/ready", timeout=10).json()["maps_loaded"] for r in replicas]
        fused = [_fused(r) for r in replicas]
        assert sum(loaded) == len(NAMES) and min(loaded) > 0, loaded
        assert sum(fused) == 3 * len(NAMES) and min(fused) > 0, fused
        before = {name: client.get(f"/maps/{name}/risk", params={"format": "npy"}).content for name in NAMES}

        replicas[0].kill()  # kill -9: nginx finds it down and sends its maps' requests to the other
        for name in NAMES:
            info = client.get(f"/maps/{name}")
            assert info.status_code == 200 and info.json()["version"] == 3, info.text
            assert client.get(f"/maps/{name}/risk", params={"format": "npy"}).content == before[name]
            assert client.post(f"/maps/{name}/scans", json={"scans": [_scan(7)]}).json()["version"] == 4
    assert httpx.get(f"{replicas[1].url}/ready", timeout=10).json()["maps_loaded"] == len(NAMES)


def test_an_imported_map_is_loaded_by_the_replica_its_name_goes_to_and_by_no_other(
        fleet: tuple[str, list[ServerProcess]]) -> None:
    from tests.app.formats.test_saved_maps import nav2_yaml, pgm, zipped

    url, replicas = fleet
    grey = np.full((40, 40), 254, dtype=np.uint8)
    grey[:, 30] = 0
    saved = zipped({"map.yaml": nav2_yaml(origin=[-2.0, -2.0, 0.0], resolution=0.1), "map.pgm": pgm(grey)})
    with httpx.Client(base_url=url, timeout=60) as client:
        for name in NAMES:
            made = client.post("/maps/import", params={"name": name}, content=saved,
                               headers={"content-type": "application/zip"})
            assert made.status_code == 201 and made.json()["version"] == 1, made.text
            assert client.post(f"/maps/{name}/scans", json={"scans": [_scan(1)]}).json()["version"] == 2
    # the import was sent where the map's own requests go: each map is held by one replica, and both hold some
    loaded = [httpx.get(f"{r.url}/ready", timeout=10).json()["maps_loaded"] for r in replicas]
    assert sum(loaded) == len(NAMES) and min(loaded) > 0, loaded
