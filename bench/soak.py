"""Soak: a long steady load; memory must stay flat after warm-up and throughput must not decay.

    python -m bench.soak --minutes 10 [--robots 2] [--warmup 1]      (from the repository root; not in CI)

The server (``python -m app``, default workers, temporary data dir) gets what
``bench.bench_load`` sends (N robots streaming 1080-beam scans into their own map and a shared
one, JSON batches and binary single scans) plus, at a slower pace, what operators do: a plan
on the shared map every 3 s and a PNG of it every 10 s. Every minute prints the server's RSS
(and its planner workers'), the scans/s of that minute, the data directory's size, errors.

Verdict, over the minutes after ``--warmup``:
  * RSS flat: last minute's server RSS within max(5%, 16 MB) of the first post-warm-up minute,
    and the fitted slope below 2 MB/min;
  * throughput steady: median scans/s of the last third >= 80% of the first third's
    (other work on a shared machine moves both thirds; a leak or a growing cost moves only one);
  * no failed request.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import psutil

from bench._client import Fleet, ServerProcess, machine
from bench.bench_load import SHARED, Workload

PLAN_EVERY_S = 3.0
PNG_EVERY_S = 10.0


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


class Load:
    """Robots, a planner and a map viewer hitting the server until :meth:`stop`."""

    def __init__(self, server: ServerProcess, work: Workload) -> None:
        self.server = server
        self.work = work
        self.lock = threading.Lock()
        self.scans = 0
        self.errors: list[str] = []
        self.plans = 0
        self._stop = threading.Event()
        self.threads = [threading.Thread(target=self._robot, args=(r,), daemon=True) for r in range(len(work.jobs))]
        self.threads.append(threading.Thread(target=self._operator, daemon=True))

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def stop(self) -> None:
        self._stop.set()
        for t in self.threads:
            t.join(timeout=120)

    def _error(self, text: str) -> None:
        with self.lock:
            self.errors.append(text)

    def _robot(self, r: int) -> None:
        jobs = self.work.jobs[r]
        with httpx.Client(base_url=self.server.url, timeout=120.0) as client:
            i = 0
            while not self._stop.is_set():
                name, batch = jobs[i % len(jobs)]
                i += 1
                try:
                    response = batch.post(client, name)
                except httpx.HTTPError as exc:
                    self._error(f"robot {r}: {exc!r}")
                    continue
                if response.status_code == 200:
                    with self.lock:
                        self.scans += len(batch.scans)
                else:
                    self._error(f"robot {r}: {response.status_code} {response.text[:120]}")

    def _operator(self) -> None:
        points = self.work.fleet.free_points
        next_plan = next_png = time.monotonic()
        k = 0
        with httpx.Client(base_url=self.server.url, timeout=120.0) as client:
            while not self._stop.wait(0.2):
                now = time.monotonic()
                try:
                    if now >= next_plan:
                        next_plan = now + PLAN_EVERY_S
                        body = {"start": points[k % len(points)].tolist(),
                                "goal": points[(k + len(points) // 2) % len(points)].tolist(),
                                "planner": "RRTConnect", "time_limit": 0.3, "robot_radius": 0.2}
                        k += 1
                        response = client.post(f"/maps/{SHARED}/plan", json=body)
                        # a start or goal a robot's new scan made occupied is a 422 the client expects
                        if response.status_code not in (200, 422):
                            self._error(f"plan: {response.status_code} {response.text[:120]}")
                        self.plans += 1
                    if now >= next_png:
                        next_png = now + PNG_EVERY_S
                        response = client.get(f"/maps/{SHARED}/risk", params={"format": "png", "scale": 2})
                        if response.status_code != 200:
                            self._error(f"png: {response.status_code}")
                except httpx.HTTPError as exc:
                    self._error(f"operator: {exc!r}")


def verdict(rss: list[float], rates: list[float], errors: int, warmup: int) -> tuple[bool, list[str]]:
    """(pass, lines) for the per-minute server RSS (MB) and scans/s after ``warmup`` minutes."""
    rss_after, rates_after = rss[warmup:], rates[warmup:]
    lines = []
    if len(rss_after) < 2:
        return False, ["too few minutes after the warm-up for a verdict"]
    growth = rss_after[-1] - rss_after[0]
    allowed = max(0.05 * rss_after[0], 16.0)
    slope = float(np.polyfit(np.arange(len(rss_after)), rss_after, 1)[0])
    rss_ok = growth <= allowed and slope < 2.0
    lines.append(f"{'PASS' if rss_ok else 'FAIL'}  RSS flat after warm-up: {rss_after[0]:.0f} -> {rss_after[-1]:.0f} MB "
                 f"(growth {growth:+.1f} MB, allowed {allowed:.0f}); slope {slope:+.2f} MB/min (< 2)")
    third = max(1, len(rates_after) // 3)
    first, last = float(np.median(rates_after[:third])), float(np.median(rates_after[-third:]))
    ratio = last / first if first else 0.0
    rate_ok = ratio >= 0.8
    lines.append(f"{'PASS' if rate_ok else 'FAIL'}  throughput steady: median scans/s first third {first:.1f}, "
                 f"last third {last:.1f} (ratio {ratio:.2f} >= 0.80)")
    lines.append(f"{'PASS' if errors == 0 else 'FAIL'}  failed requests: {errors}")
    return rss_ok and rate_ok and errors == 0, lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=1, help="minutes excluded from the verdict")
    parser.add_argument("--robots", type=int, default=2)
    parser.add_argument("--batch", type=int, default=4, help="scans per JSON batch")
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args(argv)

    print(f"machine: {machine()}")
    fleet = Fleet.generate(args.robots, 24, seed=args.seed)
    work = Workload.build(fleet, args.batch)
    server = ServerProcess(env={"FUZZYRISK_PLAN_WORKERS": "2", "FUZZYRISK_PLAN_WARMUP": "true"})
    server.start()
    print(f"server pid {server.pid} on {server.url}; {args.robots} robots + shared map; plan every {PLAN_EVERY_S:.0f} s, "
          f"PNG every {PNG_EVERY_S:.0f} s; {args.minutes} min, warm-up {args.warmup} min")
    rss: list[float] = []
    rates: list[float] = []
    load: Load | None = None
    try:
        with httpx.Client(base_url=server.url, timeout=60.0) as client:
            for name in work.maps:
                client.post("/maps", json=fleet.map_request(name)).raise_for_status()
        proc = psutil.Process(server.pid)
        load = Load(server, work)
        load.start()
        print(f"{'min':>3s} {'RSS MB':>7s} {'workers MB':>10s} {'scans/s':>8s} {'data MB':>8s} {'CPU s':>7s} "
              f"{'plans':>5s} {'errors':>6s}")
        last_scans, last_t = 0, time.perf_counter()
        for minute in range(1, args.minutes + 1):
            time.sleep(max(0.0, last_t + 60.0 - time.perf_counter()))
            now = time.perf_counter()
            with load.lock:
                scans, errors = load.scans, len(load.errors)
            rate = (scans - last_scans) / (now - last_t)
            last_scans, last_t = scans, now
            mem = proc.memory_info().rss / 2**20
            kids = sum(c.memory_info().rss for c in proc.children(recursive=True)) / 2**20
            cpu = sum(proc.cpu_times()[:2])
            rss.append(mem)
            rates.append(rate)
            assert server.data_dir is not None
            print(f"{minute:3d} {mem:7.1f} {kids:10.1f} {rate:8.1f} {_dir_bytes(server.data_dir) / 2**20:8.1f} "
                  f"{cpu:7.0f} {load.plans:5d} {errors:6d}", flush=True)
    finally:
        if load is not None:
            load.stop()
        server.close()
    errors = len(load.errors) if load else 0
    for e in (load.errors[:5] if load else []):
        print(f"  error: {e}")
    ok, lines = verdict(rss, rates, errors, args.warmup)
    print()
    for line in lines:
        print(line)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
