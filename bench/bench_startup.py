"""Start fast: the README's serve command on cold kernel caches, then again on warm ones, in one run.

``python -m bench.bench_startup [--runs 2]`` (``python3 dev.py bench startup``). Each run starts
``python3 dev.py serve`` on a new data directory (an empty numba cache, the service's own choice),
times from the command to the first scan answered, to ``/ready``, and one scan once ready; then
stops it with SIGTERM and starts it again on the same directory (warm cache) and times the same.

Targets (the service's since the first release): a first scan within 30 s of the command on cold
caches, within 1 s once ready. The warm start is the peer measured in the same run: the cold
start's extra time is the kernels' compilation, the rest is the machine. The best of ``--runs`` is
kept (a busy machine only slows a start).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
FIRST_SCAN_COLD_S = 30.0
SCAN_WHEN_READY_S = 1.0
SCAN = {"scans": [{"pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -0.6, "angle_increment": 0.1,
                   "ranges": [3.1, 3.05, 3.02, 3.0, None, 3.0, 3.0, "inf", 3.02, 3.05, 3.1, 3.16, 3.23],
                   "range_min": 0.1, "range_max": 30.0}]}


@dataclass
class Start:
    first_scan_s: float
    ready_s: float
    ready_scan_s: float


def _port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start(data: Path, name: str) -> Start:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["FUZZYRISK_VENV"] = sys.prefix
    port = _port()
    started = time.monotonic()
    process = subprocess.Popen([sys.executable, "dev.py", "serve", "--port", str(port), "--data-dir", str(data)],
                               cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=300.0) as client:
            while True:
                if process.poll() is not None:
                    raise SystemExit(f"the service ended with {process.returncode} before it answered")
                try:
                    made = client.post("/maps", json={"name": name, "resolution": 0.05, "origin": [-8.0, -5.0],
                                                      "size": [16.0, 10.0]})
                    break
                except httpx.TransportError:
                    time.sleep(0.05)
            made.raise_for_status()
            client.post(f"/maps/{name}/scans", json=SCAN).raise_for_status()
            first_scan = time.monotonic() - started
            while client.get("/ready").status_code != 200:
                time.sleep(0.1)
            ready = time.monotonic() - started
            before = time.monotonic()
            client.post(f"/maps/{name}/scans", json=SCAN).raise_for_status()
            return Start(first_scan, ready, time.monotonic() - before)
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=30)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=2, help="cold + warm starts, the best kept (default 2)")
    args = p.parse_args(argv)
    cold: list[Start] = []
    warm: list[Start] = []
    for run in range(args.runs):
        with tempfile.TemporaryDirectory(prefix="fuzzyrisk-startup-") as tmp:
            data = Path(tmp) / "data"
            cold.append(_start(data, f"cold{run}"))
            warm.append(_start(data, f"warm{run}"))
        print(f"run {run + 1}: cold first scan {cold[-1].first_scan_s:.1f} s, ready {cold[-1].ready_s:.1f} s; "
              f"warm first scan {warm[-1].first_scan_s:.1f} s, ready {warm[-1].ready_s:.1f} s", flush=True)
    best_cold = min(cold, key=lambda s: s.first_scan_s)
    best_warm = min(warm, key=lambda s: s.first_scan_s)
    once_ready = min(s.ready_scan_s for s in cold + warm)
    print("\n| start | first scan after the command | ready after | a scan once ready |")
    print("|---|---|---|---|")
    for label, s in (("cold kernel cache", best_cold), ("warm kernel cache", best_warm)):
        print(f"| {label} | {s.first_scan_s:.1f} s | {s.ready_s:.1f} s | {s.ready_scan_s * 1000:.0f} ms |")
    print(f"\ncold / warm first scan: {best_cold.first_scan_s / best_warm.first_scan_s:.1f}x")
    met = best_cold.first_scan_s < FIRST_SCAN_COLD_S and once_ready < SCAN_WHEN_READY_S
    print(f"targets (first scan < {FIRST_SCAN_COLD_S:.0f} s cold, a scan once ready < {SCAN_WHEN_READY_S:.0f} s): "
          f"{'met' if met else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
