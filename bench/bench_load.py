"""The service under load on loopback: scan throughput against in-process fusion, plan and /health latency.

    python -m bench.bench_load [--quick] [--robots N] [--seconds S] [--client lean|httpx] [--py-spy DIR]
                                                                                    (from the repository root)
    python -m bench.bench_load --fleet [--quick] ...   # = python -m bench.bench_fleet: SQLite, 1 and 2
                                                       #   replicas on one PostgreSQL

N simulated robots in one 20 m x 20 m room (``bench.bench_fusion.planar_scene``: 1080-beam
LaserScans over 270 degrees, 0.05 m maps of 420 x 420 cells) each stream their scans into their
own map and into one shared map. Even robots send JSON batches of ``--batch`` scans, odd robots
the binary upload (raw float32 ranges, one scan per request). The server is ``python -m app``
in a subprocess with its default fusion threads and planner workers, on a temporary data dir.
The robots post through one keep-alive ``http.client`` connection each (``--client lean``), as
cheap in CPU as an HTTP client gets in Python: they share the machine with the server, and a
robot does not run there (``--client httpx`` posts through httpx, about 4 times the client CPU).

Phases (``--seconds`` each; A and B alternate in ``--rounds`` short rounds so that other work on
a shared machine hits both alike):

P   over HTTP, plans alone (the planner's own latency, for comparison);
A   in process: the same batches (same sizes, same map sizes, same order per robot) fused by
    ``integrate_batch`` through a pool of as many threads as the server's fusion pool, each
    robot waiting for its batch like an HTTP client does, the shared map behind a lock that a
    robot takes before it hands the batch to the pool (as the service's turns are waited for on
    its event loop, never in a fusion thread);
B   over HTTP, scans only;                        -> ratio B / A (target >= 0.80)
C   over HTTP, scans and one client planning back to back on the shared map (no seed: a
    seeded plan is bounded by iterations, not time)  -> plan p99 <= time_limit + 100 ms.
/health is probed every 20 ms from a separate process during B and C (target p99 < 20 ms).
The service's own histograms (/metrics) split a scan request into disk commit, fusion and
the rest. The run is bounded: each phase stops at its time or after ``--max-requests`` per robot.
"""

from __future__ import annotations

import argparse
import http.client
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil

from bench._client import (
    Batch,
    Fleet,
    HealthProber,
    LeanClient,
    ServerProcess,
    machine,
    new_map,
    percentile,
    window,
)

SHARED = "shared"
FUSION_THREADS = 2  # app.config.Settings.fusion_threads default; the server is started with it explicitly


def robot_map(r: int) -> str:
    return f"robot-{r}"


@dataclass
class Workload:
    """What every robot sends, in order: (map name, batch) pairs, cycled."""

    fleet: Fleet
    batch_size: int
    jobs: list[list[tuple[str, Batch]]] = field(default_factory=list)

    @classmethod
    def build(cls, fleet: Fleet, batch_size: int) -> Workload:
        w = cls(fleet, batch_size)
        for r in range(len(fleet.scans)):
            binary = r % 2 == 1
            w.jobs.append([(name, b) for b in fleet.batches(r, batch_size, binary) for name in (robot_map(r), SHARED)])
        return w

    @property
    def maps(self) -> list[str]:
        return [robot_map(r) for r in range(len(self.jobs))] + [SHARED]


@dataclass
class PhaseResult:
    name: str
    seconds: float
    scans: int = 0
    errors: int = 0
    latency: dict[str, list[float]] = field(default_factory=lambda: {"json": [], "binary": []})
    plans: list[float] = field(default_factory=list)
    plan_status: dict[str, int] = field(default_factory=dict)
    plan_time_reported: list[float] = field(default_factory=list)
    started: float = 0.0
    ended: float = 0.0
    windows: list[tuple[float, float]] = field(default_factory=list)  # wall-clock spans of the parts

    @property
    def rate(self) -> float:
        return self.scans / self.seconds if self.seconds else 0.0


def merge(parts: list[PhaseResult], name: str) -> PhaseResult:
    """One result from the rounds of a phase (sums, and every latency sample)."""
    out = PhaseResult(name, sum(p.seconds for p in parts))
    for p in parts:
        out.scans += p.scans
        out.errors += p.errors
        for kind, lat in p.latency.items():
            out.latency[kind].extend(lat)
        out.windows.append((p.started, p.ended))
    return out


# server-side histograms read from /metrics: (metric sample name, label filter)
_SCRAPED = {
    "scan_requests": ("fuzzyrisk_http_request_duration_seconds", {"route": "/maps/{name}/scans", "method": "POST"}),
    "commit": ("fuzzyrisk_batch_commit_duration_seconds", {}),
    "fusion": ("fuzzyrisk_fusion_duration_seconds", {}),
    "plans": ("fuzzyrisk_plan_duration_seconds", {}),
    "group": ("fuzzyrisk_batch_commit_group_size", {}),  # batches per transaction, not seconds
}


def scrape(server: ServerProcess) -> dict[str, tuple[float, float]]:
    """(sum seconds, count) of the service's own timing histograms, from GET /metrics."""
    from prometheus_client.parser import text_string_to_metric_families

    text = httpx.get(f"{server.url}/metrics", timeout=30.0).text
    out = {key: (0.0, 0.0) for key in _SCRAPED}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            for key, (metric, labels) in _SCRAPED.items():
                if not sample.name.startswith(metric) or any(sample.labels.get(k) != v for k, v in labels.items()):
                    continue
                total, count = out[key]
                if sample.name == metric + "_sum":
                    out[key] = (total + sample.value, count)
                elif sample.name == metric + "_count":
                    out[key] = (total, count + sample.value)
    return out


def mean_ms(after: dict[str, tuple[float, float]], before: dict[str, tuple[float, float]]) -> dict[str, float]:
    """Mean milliseconds per observation between two scrapes."""
    means = {}
    for key in after:
        total = after[key][0] - before[key][0]
        count = after[key][1] - before[key][1]
        means[key] = 1000.0 * total / count if count else float("nan")
    return means


# ---------------------------------------------------------------- in process


def run_in_process(work: Workload, seconds: float, max_requests: int, name: str) -> PhaseResult:
    """Fuse the workload's batches in this process as the server would, for ``seconds``."""
    maps = {m: new_map(work.fleet.spec) for m in work.maps}
    lock = threading.Lock()  # the shared map takes one batch at a time, as the service's turns do
    pool = ThreadPoolExecutor(FUSION_THREADS)
    counts = [0] * len(work.jobs)
    deadline = time.perf_counter() + seconds

    def fuse(map_name: str, batch: Batch) -> int:
        scans = batch.laser_scans()  # the server builds LaserScans from each body too
        return maps[map_name].integrate_batch(scans).scans

    def robot(r: int) -> None:
        jobs = work.jobs[r]
        i = 0
        while time.perf_counter() < deadline and i < max_requests:
            map_name, batch = jobs[i % len(jobs)]
            if map_name == SHARED:
                # the wait for the shared map happens here, in the robot's thread, as the service waits
                # for a turn on its event loop: a fusion thread never sits blocked on the lock
                with lock:
                    counts[r] += pool.submit(fuse, map_name, batch).result()
            else:
                counts[r] += pool.submit(fuse, map_name, batch).result()
            i += 1

    t0 = time.perf_counter()
    threads = [threading.Thread(target=robot, args=(r,)) for r in range(len(work.jobs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    elapsed = time.perf_counter() - t0
    pool.shutdown()
    return PhaseResult(name, elapsed, scans=sum(counts))


# ---------------------------------------------------------------- over HTTP


@contextmanager
def robot_client(url: str, kind: str) -> Iterator[Callable[[str, Batch], bool]]:
    """A robot's upload function, ``post(map name, batch) -> answered 200``, over its own connection."""
    if kind == "lean":
        with LeanClient(url, timeout=60.0) as lean:

            def post_lean(map_name: str, batch: Batch) -> bool:
                try:
                    return lean.post(map_name, batch) == 200
                except (OSError, http.client.HTTPException):
                    return False

            yield post_lean
        return
    with httpx.Client(base_url=url, timeout=60.0) as pooled:

        def post_httpx(map_name: str, batch: Batch) -> bool:
            try:
                return batch.post(pooled, map_name).status_code == 200
            except httpx.HTTPError:
                return False

        yield post_httpx


def run_http(server: ServerProcess, work: Workload, seconds: float, max_requests: int, name: str,
             plan_body: dict[str, Any] | None, *, robots: bool = True, seeded: bool = False,
             client: str = "lean") -> PhaseResult:
    """Stream the workload to the server for ``seconds`` (and plan back to back if ``plan_body``).

    ``robots=False``: plans only (the planner's own latency, for comparison). ``seeded``: plans carry
    a seed, which bounds them by iterations instead of wall time (planning.ompl_solve), so they take
    longer than ``time_limit`` when the CPU is shared. ``client``: the robots' HTTP client, ``lean``
    (:class:`bench._client.LeanClient`) or ``httpx``.
    """
    result = PhaseResult(name, seconds)
    lock = threading.Lock()
    deadline = time.perf_counter() + seconds
    stop = threading.Event()

    def robot(r: int) -> None:
        jobs = work.jobs[r]
        with robot_client(server.url, client) as post:
            i = 0
            while time.perf_counter() < deadline and i < max_requests:
                map_name, batch = jobs[i % len(jobs)]
                t0 = time.perf_counter()
                ok = post(map_name, batch)
                dt = time.perf_counter() - t0
                with lock:
                    if ok:
                        result.scans += len(batch.scans)
                        result.latency[batch.kind].append(dt)
                    else:
                        result.errors += 1
                i += 1

    def planner() -> None:
        assert plan_body is not None
        with httpx.Client(base_url=server.url, timeout=120.0) as planning:
            k = 0
            while not stop.is_set():
                points = work.fleet.free_points
                body = {**plan_body, "start": points[k % len(points)].tolist(),
                        "goal": points[(k + len(points) // 2) % len(points)].tolist()}
                if seeded:
                    body["seed"] = k
                t0 = time.perf_counter()
                try:
                    response = planning.post(f"/maps/{SHARED}/plan", json=body)
                    status = str(response.status_code)
                    if response.status_code == 200:
                        status = response.json()["status"]
                        result.plan_time_reported.append(response.json()["planning_time"])
                    elif response.status_code == 422 and isinstance(response.json().get("detail"), dict):
                        status = response.json()["detail"]["code"]
                except httpx.HTTPError as exc:
                    status = type(exc).__name__
                dt = time.perf_counter() - t0
                if not stop.is_set() or status in ("exact", "approximate", "none"):
                    result.plans.append(dt)
                    result.plan_status[status] = result.plan_status.get(status, 0) + 1
                k += 1

    result.started = time.time()
    t0 = time.perf_counter()
    threads = [threading.Thread(target=robot, args=(r,)) for r in range(len(work.jobs))] if robots else []
    plan_thread = threading.Thread(target=planner) if plan_body is not None else None
    if plan_thread is not None:
        plan_thread.start()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if not robots:
        time.sleep(max(0.0, deadline - time.perf_counter()))
    result.seconds = time.perf_counter() - t0  # the last requests may end after the deadline
    result.ended = time.time()
    stop.set()
    if plan_thread is not None:
        plan_thread.join()
    return result


class ResourceSampler:
    """CPU % and RSS of the server process (and of its children: planner workers), every 0.5 s."""

    def __init__(self, pid: int) -> None:
        self.proc = psutil.Process(pid)
        self.samples: list[tuple[float, float, float, float]] = []  # time, cpu %, rss MB, children rss MB
        self._stop = threading.Event()
        self.proc.cpu_percent(None)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            try:
                cpu = self.proc.cpu_percent(None)
                rss = self.proc.memory_info().rss / 2**20
                kids = sum(c.memory_info().rss for c in self.proc.children(recursive=True)) / 2**20
            except psutil.Error:
                continue
            self.samples.append((time.time(), cpu, rss, kids))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def summary(self, windows: list[tuple[float, float]]) -> str:
        """Means and maxima over the samples taken inside ``windows`` (wall-clock spans)."""
        rows = [s for s in self.samples if any(start <= s[0] < end for start, end in windows)]
        if not rows:
            return "no samples"
        cpu = [r[1] for r in rows]
        rss = [r[2] for r in rows]
        kids = [r[3] for r in rows]
        return (f"server CPU {sum(cpu) / len(cpu):.0f}% mean, {max(cpu):.0f}% max (100% = one core); "
                f"RSS {sum(rss) / len(rss):.0f} MB mean, {max(rss):.0f} MB max; planner workers RSS {max(kids):.0f} MB")


def _ms(values: list[float], q: float) -> str:
    return f"{percentile(values, q) * 1000:7.1f}"


def _verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def _py_spy(pid: int, seconds: float, out: Path, *extra: str) -> subprocess.Popen[bytes] | None:
    exe = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(exe).exists():
        print("  (py-spy not installed: .venv/bin/pip install py-spy)")
        return None
    out.parent.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen([exe, "record", "-p", str(pid), "-d", str(int(seconds)), "-r", "50", "--nonblocking",
                             "--threads", "-f", "raw", "-o", str(out), *extra],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def main(argv: list[str] | None = None) -> int:
    args_in = sys.argv[1:] if argv is None else argv
    if "--fleet" in args_in:  # SQLite, 1 and 2 replicas on one PostgreSQL (bench/bench_fleet.py)
        from bench import bench_fleet

        return bench_fleet.main([a for a in args_in if a != "--fleet"])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 robots, 8 s phases")
    parser.add_argument("--fleet", action="store_true",
                        help="run bench/bench_fleet.py instead (its own options follow; see its --help)")
    parser.add_argument("--robots", type=int, default=None, help="simulated robots (default 4, quick 2)")
    parser.add_argument("--batch", type=int, default=4, help="scans per JSON batch")
    parser.add_argument("--seconds", type=float, default=None, help="length of each phase (default 30, quick 8)")
    parser.add_argument("--max-requests", type=int, default=20_000, help="per robot and phase")
    parser.add_argument("--rounds", type=int, default=None, help="A/B alternations (default 3, quick 2)")
    parser.add_argument("--planner", default="RRTstar")
    parser.add_argument("--time-limit", type=float, default=0.5, help="plan time_limit, seconds")
    parser.add_argument("--seeded", action="store_true",
                        help="plans carry a seed (bounded by iterations, not wall time: see planning.ompl_solve)")
    parser.add_argument("--seed", type=int, default=5, help="of the simulated room and robots")
    parser.add_argument("--client", choices=("lean", "httpx"), default="lean",
                        help="the robots' HTTP client (see the docstring)")
    parser.add_argument("--py-spy", type=Path, default=None,
                        help="record py-spy (raw collapsed stacks) of the server during B and C into this directory")
    args = parser.parse_args(argv)
    robots = args.robots or (2 if args.quick else 4)
    seconds = args.seconds or (8.0 if args.quick else 30.0)
    rounds = args.rounds or (2 if args.quick else 3)

    print(f"machine: {machine()}")
    fleet = Fleet.generate(robots, 24, seed=args.seed)
    work = Workload.build(fleet, args.batch)
    print(f"{robots} robots, 1080-beam scans; even robots: JSON batches of {args.batch}, odd robots: binary, "
          f"1 scan a request; every batch goes to the robot's map and to '{SHARED}'; maps {fleet.spec.shape} "
          f"cells at {fleet.spec.resolution} m; phases of {seconds:.0f} s; robots post through {args.client}")
    plan_body = {"planner": args.planner, "time_limit": args.time_limit, "state_space": "R2", "robot_radius": 0.2,
                 "max_risk": 0.6, "risk_weight": 1.0, "allow_unknown": True}

    # warm up the numba kernels in this process before timing anything
    warm = new_map(fleet.spec)
    for _, batch in work.jobs[0][:2] + (work.jobs[1][:2] if robots > 1 else []):
        warm.integrate_batch(batch.laser_scans())
    warm.risk()

    env = {"FUZZYRISK_PLAN_WORKERS": "2", "FUZZYRISK_PLAN_WARMUP": "true",
           "FUZZYRISK_FUSION_THREADS": str(FUSION_THREADS)}
    server = ServerProcess(env=env)
    t0 = time.perf_counter()
    server.start()
    print(f"server pid {server.pid} up in {time.perf_counter() - t0:.1f} s ({server.url}, data {server.data_dir})")
    try:
        with httpx.Client(base_url=server.url, timeout=120.0) as client:
            for name in work.maps:
                client.post("/maps", json=fleet.map_request(name)).raise_for_status()
            for r in range(robots):  # compile the server's kernels on both paths
                for map_name, batch in work.jobs[r][:2]:
                    batch.post(client, map_name).raise_for_status()
            warm_plan = {**plan_body, "start": fleet.free_points[0].tolist(), "goal": fleet.free_points[1].tolist(),
                         "seed": 0}
            client.post(f"/maps/{SHARED}/plan", json=warm_plan)
        sampler = ResourceSampler(server.pid)

        p0 = run_http(server, work, min(seconds, 6.0), args.max_requests, "P plans alone", plan_body,
                      robots=False, seeded=args.seeded)
        prober = HealthProber(server.url)
        spies = []
        if args.py_spy:
            spies = [_py_spy(server.pid, 3 * seconds + 10, args.py_spy / "server.raw"),
                     _py_spy(server.pid, 3 * seconds + 10, args.py_spy / "server-gil.raw", "--gil")]
        # A and B alternate in short rounds so that other work on the machine hits both alike
        a_parts, b_parts = [], []
        server_ms: dict[str, list[dict[str, float]]] = {"B": [], "C": []}
        part = seconds / rounds
        for r in range(rounds):
            a_parts.append(run_in_process(work, part, args.max_requests, f"A{r + 1}"))
            before = scrape(server)
            b_parts.append(run_http(server, work, part, args.max_requests, f"B{r + 1}", None, client=args.client))
            server_ms["B"].append(mean_ms(scrape(server), before))
        before = scrape(server)
        c = run_http(server, work, seconds, args.max_requests, "C HTTP scans + plans", plan_body,
                     seeded=args.seeded, client=args.client)
        server_ms["C"].append(mean_ms(scrape(server), before))
        c.windows.append((c.started, c.ended))
        health, health_failures = prober.stop()
        for spy in spies:
            if spy is not None:
                spy.wait()
        if spies:
            print(f"  py-spy: {args.py_spy}/server.raw (active threads), server-gil.raw (the GIL holder)")
        sampler.stop()
        server_alive = server.alive()
    finally:
        server.close()

    a = merge(a_parts, f"A in process ({rounds} rounds)")
    b = merge(b_parts, f"B HTTP scans ({rounds} rounds)")
    inproc = a.rate
    print(f"\n{'phase':28s} {'scans':>7s} {'s':>6s} {'scans/s':>8s} {'errors':>6s}   per round")
    for p, parts in ((a, a_parts), (b, b_parts), (c, [c])):
        rates = " ".join(f"{q.rate:.0f}" for q in parts)
        print(f"{p.name:28s} {p.scans:7d} {p.seconds:6.1f} {p.rate:8.1f} {p.errors:6d}   {rates}")
    print("\nlatency, ms                      n     p50     p99     max")
    for p in (b, c):
        for kind, lat in p.latency.items():
            label = f"{p.name[:1]} scan batch ({kind}{', ' + str(args.batch) + ' scans' if kind == 'json' else ''})"
            print(f"  {label:28s} {len(lat):5d} {_ms(lat, 50)} {_ms(lat, 99)} {_ms(lat, 100)}")
    seeded = ", seeded" if args.seeded else ""
    for p in (p0, c):
        print(f"  {p.name[:1] + ' plan (' + args.planner + ', ' + str(args.time_limit) + ' s' + seeded + ')':28s} "
              f"{len(p.plans):5d} {_ms(p.plans, 50)} {_ms(p.plans, 99)} {_ms(p.plans, 100)}   statuses {p.plan_status}")
        if p.plan_time_reported:
            print(f"  {'  planning_time reported':28s} {len(p.plan_time_reported):5d} {_ms(p.plan_time_reported, 50)} "
                  f"{_ms(p.plan_time_reported, 99)} {_ms(p.plan_time_reported, 100)}")
    h_b = [v for start, end in b.windows for v in window(health, start, end)]
    h_c = window(health, c.started, c.ended)
    h_all = h_b + h_c
    for label, h in (("/health during B", h_b), ("/health during C", h_c), ("/health throughout B+C", h_all)):
        print(f"  {label:28s} {len(h):5d} {_ms(h, 50)} {_ms(h, 99)} {_ms(h, 100)}")
    print(f"  /health failures: {health_failures}")
    for phase, rows in server_ms.items():
        mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}  # NaN where nothing was observed
        print(f"server's own timings during {phase}, mean ms per scan request: answer {mean['scan_requests']:.1f} = "
              f"disk commit {mean['commit']:.1f} + fusion {mean['fusion']:.1f} + the rest (turn wait, parse, "
              f"encode, framework) {mean['scan_requests'] - mean['commit'] - mean['fusion']:.1f}; a commit of a "
              f"batch queued behind another overlaps that one's fusion; {mean['group'] / 1000:.2f} batches per "
              f"commit transaction" + (f"; plan answer {mean['plans']:.0f}" if phase == "C" else ""))
    print(f"\nresources during B: {sampler.summary(b.windows)} (its rounds only, not the A rounds between)")
    print(f"resources during C: {sampler.summary([(c.started, c.ended)])}")

    ratio = b.rate / inproc if inproc else 0.0
    plan_p99 = percentile(c.plans, 99)
    health_p99 = percentile(h_all, 99)
    targets = [
        (f"HTTP fuses >= 80% of in-process scans/s: B {b.rate:.1f} / A {inproc:.1f} = {ratio:.2f}", ratio >= 0.8),
        (f"plan p99 under scan load <= time_limit + 100 ms: {plan_p99 * 1000:.0f} ms <= "
         f"{(args.time_limit + 0.1) * 1000:.0f} ms", bool(c.plans) and plan_p99 <= args.time_limit + 0.1),
        (f"/health p99 throughout < 20 ms: {health_p99 * 1000:.1f} ms", bool(h_all) and health_p99 < 0.020),
        (f"no failed request (scans {b.errors + c.errors}, /health {health_failures}), server alive",
         b.errors + c.errors + health_failures == 0 and server_alive),
    ]
    print()
    for text, ok in targets:
        print(f"{_verdict(ok)}  {text}")
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")
    return 0 if all(ok for _, ok in targets) else 1


if __name__ == "__main__":
    sys.exit(main())
