"""Start and stop clean: the README's command on cold caches, SIGTERM, kill -9.

The times are printed (``pytest -s`` shows them); their targets are ``bench/bench_startup.py``'s, measured
beside a warm start in the same run (a test that timed them failed on a busy machine, not on a slow service).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest

from tests.e2e.conftest import CHILDREN_GRACE_S, PATIENCE_S, ROOT, Server, assert_ended, free_port

pytestmark = pytest.mark.slow

SCAN = {"scans": [{"pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -0.6, "angle_increment": 0.1,
                   "ranges": [3.1, 3.05, 3.02, 3.0, None, 3.0, 3.0, "inf", 3.02, 3.05, 3.1, 3.16, 3.23],
                   "range_min": 0.1, "range_max": 30.0}]}


def _map(name: str) -> dict[str, Any]:
    return {"name": name, "resolution": 0.05, "origin": [-8.0, -5.0], "size": [16.0, 10.0]}


def test_the_readme_command_answers_a_first_scan_on_cold_caches_caches_its_kernels_and_ends_on_sigterm(
    tmp_path: Path,
) -> None:
    """``python3 dev.py serve`` on a new data directory (so an empty kernel cache, chosen by the service), as
    a user runs it: the first scan is timed from the command, then readiness, then a scan once ready; SIGTERM
    to the command ends the server and every process it started."""
    data = tmp_path / "data"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}  # the service's own choice
    env["FUZZYRISK_VENV"] = sys.prefix  # the environment this suite runs in: installed already
    command = [sys.executable, "dev.py", "serve", "--port", str(free_port()), "--data-dir", str(data)]
    # "the end of the install": dev.py installs if it must, then the service prints its help and exits
    subprocess.run([*command, "--help"], cwd=ROOT, env=env, check=True, capture_output=True, timeout=600)

    log_path = tmp_path / "serve.log"
    started = time.monotonic()
    with log_path.open("wb") as log:
        process = subprocess.Popen(command, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        url = f"http://127.0.0.1:{command[command.index('--port') + 1]}"
        with httpx.Client(base_url=url, timeout=120.0) as client:
            while True:  # refused until the service listens
                assert process.poll() is None, log_path.read_text()
                try:
                    created = client.post("/maps", json=_map("lab"))
                    break
                except httpx.TransportError:
                    time.sleep(0.05)
            assert created.status_code == 201, created.text
            fused = client.post("/maps/lab/scans", json=SCAN)
            assert fused.status_code == 200, fused.text
            first_scan_s = time.monotonic() - started

            while client.get("/ready").status_code != 200:
                assert process.poll() is None, log_path.read_text()
                assert time.monotonic() - started < 300, client.get("/ready").json()
                time.sleep(0.1)
            ready_s = time.monotonic() - started
            assert client.post("/maps", json=_map("hall")).status_code == 201
            before = time.monotonic()
            assert client.post("/maps/hall/scans", json=SCAN).status_code == 200
            ready_scan_s = time.monotonic() - before
            planned = client.post("/maps/lab/plan", json={"start": [-6, -3], "goal": [6, 3], "planner": "RRTConnect",
                                                          "time_limit": 1.0})
            assert planned.status_code == 200 and planned.json()["status"] == "exact", planned.text
        print(f"\n`python3 dev.py serve`, cold kernel cache: first scan answered {first_scan_s:.1f} s after the "
              f"command, ready after {ready_s:.1f} s, a scan once ready in {ready_scan_s * 1000:.0f} ms")
        assert any((data / "numba-cache").rglob("*.nbi")), "the kernels are cached in the data directory"

        children = psutil.Process(process.pid).children(recursive=True)
        assert len(children) >= 3, children  # forkserver, planner workers, resource tracker (dev.py exec'd)
        stopped = time.monotonic()
        process.send_signal(signal.SIGTERM)
        code = process.wait(timeout=60)
        assert code in (0, -signal.SIGTERM), log_path.read_text()
        assert_ended(children, CHILDREN_GRACE_S)
        print(f"SIGTERM: the server and its {len(children)} processes ended in {time.monotonic() - stopped:.1f} s")
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=30)


def test_after_kill_9_of_the_server_none_of_its_children_is_alive_10_s_later(start_server: Any) -> None:
    """Planner workers up (one in the middle of a long plan, holding the GIL in OMPL), then SIGKILL."""
    server: Server = start_server(FUZZYRISK_PLAN_WARMUP="true", FUZZYRISK_PLAN_WORKERS="2")
    with server.client() as client:
        assert client.post("/maps", json=_map("lab")).status_code == 201
        assert client.post("/maps/lab/scans", json=SCAN).status_code == 200
    children = server.children()
    workers = [c for c in children if "forkserver" in " ".join(c.cmdline()) and c.ppid() != server.process.pid]
    assert len(workers) == 2, [c.cmdline() for c in children]

    def long_plan() -> None:
        try:
            httpx.post(f"{server.url}/maps/lab/plan", timeout=60.0, json={
                "start": [-6, -3], "goal": [6, 3], "planner": "RRTstar", "time_limit": 20.0})
        except httpx.HTTPError:
            pass  # the server is killed under it

    planning = threading.Thread(target=long_plan)
    planning.start()
    deadline = time.monotonic() + PATIENCE_S
    while not any(w.cpu_percent(interval=0.2) > 20 for w in workers):  # until a worker is in the plan's solve
        assert time.monotonic() < deadline, "no worker took up the plan"
    killed = time.monotonic()
    server.process.kill()
    server.process.wait(timeout=30)
    _, alive = psutil.wait_procs(children, timeout=CHILDREN_GRACE_S)
    took = time.monotonic() - killed
    planning.join(timeout=60)
    assert_ended(alive, 0.1)
    print(f"\nkill -9: the server's {len(children)} processes (forkserver, 2 workers, resource tracker) ended "
          f"within {took:.2f} s")
