"""A 3-D lidar's clouds over HTTP: sustained clouds/s and rays/s, against in-process fusion and OctoMap.

    python3 dev.py bench lidar [--quick] [--seconds S] [--cases ouster@0.1,os1-128@0.1] [--data DIR]
    python -m bench.bench_lidar ...                                    (from the repository root)

One ``python -m app`` on loopback (``bench._client.ServerProcess``). For each case (a cloud source at a
resolution, a growing 3-D map of its own, default engine):

1. a robot posts its clouds for ``--seconds`` (60), each a ``sensor_msgs/PointCloud2`` CDR body
   (``app.ros.messages_in``: x, y, z, intensity float32, the sensor pose and ``range_max`` in the query, its
   ``header.stamp`` at 10 Hz), with two requests in flight, as a ROS node publishing at 10 Hz would be: the
   next cloud leaves while the previous one is answered. The stream may slow, never drop a cloud: a 503 is
   retried after a pause, every cloud must be acknowledged with its own map version (the run stops otherwise);
2. meanwhile another client (its own process) asks, once a second, for an R3 plan (``POST /maps/{name}/plan``,
   RRTConnect, seeded) between two sensor positions where the robot now is, and reads the risk of a 10 x 10 x 4 m
   window around it (``risk.npy?min=..&max=..``): its p99 during the stream against its p99 before the stream
   (the map then holding the first clouds, ``PRIME``), unloaded;
3. the same clouds, in the order the service applied them (their versions), fused in this process
   (``FuzzyMap.integrate_batch``, a cloud a call, the same map kind), timed for ``--in-process-seconds``, the rest
   untimed; the service's map must be it, cell for cell (``risk.npy`` and ``layer=observed``);
4. OctoMap (``OcTree.insertPointCloud``, the same map-frame points, origin and ``range_max``) on the same clouds
   until ``--octomap-seconds`` have passed (at least one cloud): its points/s.

Clouds: ``os1-64`` and ``os1-128``, the synthetic room of ``bench fusion`` (``bench_fusion.lidar_scene``: its
scene (b) for ``os1-64``, the same room and sensor positions swept by 128 rings), ``SYNTHETIC_SWEEPS`` sweeps
replayed in a loop; ``ouster``, the three real OS-1-128 frames of ``ouster/`` in the data directory
(``bench_extent.ouster_frames``), rows at the origin (no return) dropped, ``range_max`` 30 m, every height,
replayed in a loop along their poses, each loop ``LOOP_SHIFT_M`` farther along x, so that every frame meets
unobserved space as on a drive; that map forgets what lies ``OUSTER_FORGET_BEYOND_M`` behind (``forget_beyond``:
without it a drive outgrows ``FUZZYRISK_MAX_MAP_CELLS`` on its second loop). Printed: clouds/s and rays/s over
HTTP, in-process and OctoMap's, post latency p50/p99, plan and read p99 loaded against unloaded, the CPU
seconds of the server (its event loop, its pool threads, its child processes), of both clients, and the load
average; then the targets (``TARGETS``).
"""

from __future__ import annotations

import argparse
import http.client
import json
import math
import multiprocessing
import os
import struct
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import httpx
import numpy as np
import psutil
from scipy.spatial.transform import Rotation

from app.ros import messages_in
from app.ros.msgtypes import typestore
from bench import _data, bench_extent, bench_fusion
from bench._client import LeanClient, ServerProcess, machine, npy_array, percentile, wait_ready
from bench.bench_fusion import Clock
from bench.bench_load import mean_ms, scrape
from fuzzyocc import FuzzyMap, LatticeSpec, PointCloud, SensorModel

SECONDS = 60.0
QUICK_SECONDS = 3.0
UNLOADED_S = 10.0  # the plan-and-read client alone, before the stream
QUICK_UNLOADED_S = 2.0
IN_PROCESS_S = 30.0
OCTOMAP_S = 15.0
IN_FLIGHT = 2  # requests a robot has in flight: the next cloud leaves while the previous one is answered
RATE_HZ = 10.0  # the stamps' rate, as the sensor sweeps
RETRY_PAUSE_S = 0.05  # after a 503 (the map's line full), before the same cloud again
RANGE_MAX_M = 30.0
SYNTHETIC_SWEEPS = 10
QUICK_SYNTHETIC_SWEEPS = 2
SEED = 7  # bench fusion's: its scene (b) is os1-64 here
LOOP_SHIFT_M = 200.0
OUSTER_FORGET_BEYOND_M = 50.0  # beyond range_max and a loop's own motion (0.75 m): only past loops are forgotten
PRIME = {"ouster": 3, "os1-64": 2, "os1-128": 2}  # clouds fused before the unloaded window: a map to plan on
PLAN_EVERY_S = 1.0
PLAN = {"planner": "RRTConnect", "time_limit": 1.0, "seed": 1, "robot_radius": 0.3}
READ_HALF_M = (5.0, 5.0, 2.0)  # the read window around the robot
FRAME_ID = "os_sensor"
CASES = ("ouster@0.1", "ouster@0.2", "os1-64@0.1", "os1-128@0.1", "os1-64@0.2", "os1-128@0.2")
QUICK_CASES = ("ouster@0.2", "os1-64@0.2")
#: (figure, case, threshold): what the lead set for this bench.
TARGET_OUSTER_CLOUDS_S = 10.0
TARGET_OS1_128_RAYS_S = 1.31e6
TARGET_POST_P99_S = 0.3
TARGET_LOADED_X = 3.0
TARGET_VS_OCTOMAP = 20.0


# ---------------------------------------------------------------- the clouds


@dataclass(frozen=True)
class Sweep:
    """One sensor sweep as the robot holds it: float32 rows ``x y z intensity`` in the sensor frame, the sensor
    pose in the map frame, and its CDR body (a ``sensor_msgs/PointCloud2``, stamped when sent)."""

    rows: np.ndarray  # (N, 4) float32
    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]  # x, y, z, w
    body: bytes = field(repr=False)

    @property
    def rays(self) -> int:
        return int(self.rows.shape[0])


def cloud_body(rows: np.ndarray) -> bytes:
    """The CDR bytes of an unorganised PointCloud2 of float32 ``x y z intensity`` rows (stamp 0: :func:`stamped`)."""
    store = typestore()
    types = store.types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                          frame_id=FRAME_ID)
    fields = [types["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
              for i, n in enumerate(("x", "y", "z", "intensity"))]
    rows = np.ascontiguousarray(rows, dtype="<f4")
    msg = types[messages_in.POINT_CLOUD2](
        header=header, height=1, width=rows.shape[0], fields=fields, is_bigendian=False, point_step=16,
        row_step=16 * rows.shape[0], data=rows.view(np.uint8).reshape(-1), is_dense=True)
    return messages_in.encode(msg, messages_in.POINT_CLOUD2)


def stamped(body: bytes, stamp_ns: int) -> bytes:
    """``body`` with its ``header.stamp`` set: the stamp is the message's first field, after CDR's 4-byte header."""
    out = bytearray(body)
    struct.pack_into("<iI", out, 4, stamp_ns // 10**9, stamp_ns % 10**9)
    return bytes(out)


def sweep(rows: np.ndarray, position: Sequence[float], quaternion: Sequence[float]) -> Sweep:
    rows = np.ascontiguousarray(rows, dtype=np.float32)
    return Sweep(rows, tuple(float(v) for v in position), tuple(float(v) for v in quaternion),  # type: ignore[arg-type]
                 cloud_body(rows))


def synthetic_sweeps(rings: int, count: int) -> list[Sweep]:
    """``count`` sweeps of ``rings`` x 1024 rays in bench fusion's room: its scene (b) at 64 rings (the same seed,
    drawn after its planar scene), the same room and sensor positions at any ring count. The sensor frame is the
    map's axes at the sweep's origin."""
    rng = np.random.default_rng(SEED)
    bench_fusion.planar_scene(rng, 30)
    scene = bench_fusion.lidar_scene(rng, count, rings=rings)
    out = []
    for origin, points in zip(scene.origins, scene.points):
        rows = np.zeros((points.shape[0], 4), dtype=np.float32)
        rows[:, :3] = points - origin
        out.append(sweep(rows, origin, (0.0, 0.0, 0.0, 1.0)))
    return out


def ouster_sweeps(folder: Path) -> list[Sweep]:
    """The Ouster frames of ``folder`` (``bench_extent.ouster_frames``) at their poses."""
    return [sweep(f.rows, f.translation, Rotation.from_matrix(f.rotation).as_quat())
            for f in bench_extent.ouster_frames(folder)]


@dataclass(frozen=True)
class Source:
    """A case's clouds: cloud ``k`` of the stream is sweep ``k % n`` moved ``shift_m`` along x per loop."""

    kind: str
    sweeps: list[Sweep]
    shift_m: float  # per loop
    forget_beyond: float | None

    def offset(self, k: int) -> float:
        return (k // len(self.sweeps)) * self.shift_m

    def position(self, k: int) -> tuple[float, float, float]:
        x, y, z = self.sweeps[k % len(self.sweeps)].position
        return (x + self.offset(k), y, z)

    def rays(self, k: int) -> int:
        return self.sweeps[k % len(self.sweeps)].rays

    def query(self, k: int) -> dict[str, float]:
        """The query of cloud ``k``'s upload: the sensor pose ``T_map_sensor`` and ``range_max``."""
        qx, qy, qz, qw = self.sweeps[k % len(self.sweeps)].quaternion
        x, y, z = self.position(k)
        return {"x": x, "y": y, "z": z, "qx": qx, "qy": qy, "qz": qz, "qw": qw, "range_max": RANGE_MAX_M}

    def target(self, name: str, k: int) -> str:
        return f"/maps/{name}/scans?{urlencode(self.query(k))}"

    def body(self, k: int, t0_ns: int) -> bytes:
        return stamped(self.sweeps[k % len(self.sweeps)].body, t0_ns + round(k * 1e9 / RATE_HZ))

    def cloud(self, k: int) -> PointCloud:
        """Cloud ``k`` as the service makes it of the upload: float32 sensor-frame points placed at its pose."""
        s = self.sweeps[k % len(self.sweeps)]
        return PointCloud.from_sensor_frame(s.rows[:, :3].astype(np.float64), self.position(k), s.quaternion,
                                            RANGE_MAX_M, max_rays=max(s.rays, 1))


def source(kind: str, quick: bool) -> Source:
    if kind == "ouster":
        return Source(kind, ouster_sweeps(_data.needed("ouster")), LOOP_SHIFT_M, OUSTER_FORGET_BEYOND_M)
    rings = {"os1-64": 64, "os1-128": 128}[kind]
    return Source(kind, synthetic_sweeps(rings, QUICK_SYNTHETIC_SWEEPS if quick else SYNTHETIC_SWEEPS), 0.0, None)


def growing_map(resolution: float, forget_beyond: float | None) -> FuzzyMap:
    """The in-process map of a case: what ``map_request`` makes on the service."""
    m = FuzzyMap(LatticeSpec(3, resolution), SensorModel())
    m.forget_beyond = forget_beyond
    return m


def map_request(name: str, resolution: float, forget_beyond: float | None) -> dict[str, Any]:
    return {"name": name, "dimensions": 3, "resolution": resolution, "extent": "growing",
            "forget_beyond": forget_beyond}


# ---------------------------------------------------------------- the stream


@dataclass(frozen=True)
class Ack:
    """One cloud's upload: its index in the stream, when it left and was answered, the map version it made."""

    k: int
    sent: float
    answered: float
    version: int
    retries: int

    @property
    def latency(self) -> float:
        return self.answered - self.sent


class Stream:
    """``IN_FLIGHT`` threads, each on its own connection, posting the next cloud of ``src`` as soon as its own
    answer came, until ``seconds`` have passed since :meth:`run` began (the clouds in flight are awaited)."""

    def __init__(self, url: str, name: str, src: Source, first: int, robot_at: Any = None) -> None:
        self.url, self.name, self.src = url, name, src
        self.robot_at = robot_at  # a shared double: the x offset of the last acknowledged cloud (for the planner)
        self._next = first
        self._lock = threading.Lock()
        self.acks: list[Ack] = []
        self.failures: list[str] = []
        self.sent = 0
        self.t0_ns = time.time_ns()

    def _take(self, until: float) -> int | None:
        with self._lock:
            if time.perf_counter() >= until or self.failures:
                return None
            k, self._next = self._next, self._next + 1
            self.sent += 1
            return k

    def post(self, client: LeanClient, k: int) -> Ack:
        """Cloud ``k`` until acknowledged: a 503 is retried after ``RETRY_PAUSE_S``; anything else is a failure."""
        body, target = self.src.body(k, self.t0_ns), self.src.target(self.name, k)
        sent, retries = time.perf_counter(), 0
        while True:
            status, answer = client.send("POST", target, body, messages_in.media_type(messages_in.POINT_CLOUD2))
            if status == 200:
                return Ack(k, sent, time.perf_counter(), int(json.loads(answer)["version"]), retries)
            if status != 503:
                raise RuntimeError(f"cloud {k}: {status} {answer[:300]!r}")
            retries += 1
            time.sleep(RETRY_PAUSE_S)

    def _robot(self, until: float) -> None:
        with LeanClient(self.url) as client:
            while (k := self._take(until)) is not None:
                try:
                    ack = self.post(client, k)
                except Exception as exc:  # noqa: BLE001 - every failure is reported, and stops the stream
                    with self._lock:
                        self.failures.append(f"{type(exc).__name__}: {exc}")
                    return
                with self._lock:
                    self.acks.append(ack)
                    if self.robot_at is not None:  # the answers of the two threads may come in either order
                        self.robot_at.value = max(self.robot_at.value, self.src.offset(k))

    def run(self, seconds: float) -> tuple[float, float]:
        """Stream for ``seconds``; (start, end) on ``time.perf_counter``, the end the last answer."""
        start = time.perf_counter()
        threads = [threading.Thread(target=self._robot, args=(start + seconds,)) for _ in range(IN_FLIGHT)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return start, max((a.answered for a in self.acks), default=time.perf_counter())

    def check(self, first: int) -> list[Ack]:
        """The acknowledgements in the order the service applied them; ``RuntimeError`` unless every cloud sent was
        acknowledged once, each with its own version."""
        acks = sorted(self.acks, key=lambda a: a.version)
        if self.failures or len(acks) != self.sent:
            raise RuntimeError(f"{self.name}: {len(acks)} of {self.sent} clouds acknowledged; "
                               f"failures: {self.failures[:3]}")
        if sorted(a.k for a in acks) != list(range(first, first + self.sent)):
            raise RuntimeError(f"{self.name}: the clouds acknowledged are not the clouds sent")
        if len({a.version for a in acks}) != len(acks):
            raise RuntimeError(f"{self.name}: two clouds acknowledged with one version")
        return acks


# ---------------------------------------------------------------- the planner and reader beside it


Sample = tuple[float, str, float, int, str]  # when, plan or read, seconds, HTTP status, a plan's status


def _outcome(kind: str, status: int, answer: bytes) -> str:
    """A plan's status (exact, approximate, none), or a refusal's HTTP status and error code; "" for a read's 200."""
    if status == 200:
        return str(json.loads(answer)["status"]) if kind == "plan" else ""
    try:
        code = json.loads(answer).get("code", "")
    except ValueError:
        code = ""
    return f"HTTP {status} {code}".strip() if status else "no answer (connection)"


def _every_second(url: str, kind: str, request: Any, stop: Any, samples: list[Sample]) -> None:
    """``request()`` -> (method, target, body), sent every ``PLAN_EVERY_S`` on a connection of its own until ``stop``;
    the next at once when one took longer."""
    client = LeanClient(url)
    tick = time.perf_counter()
    while not stop.is_set():
        method, target, body = request()
        at, t0 = time.time(), time.perf_counter()
        try:
            status, answer = client.send(method, target, body)
        except (OSError, http.client.HTTPException):
            status, answer = 0, b""
        samples.append((at, kind, time.perf_counter() - t0, status, _outcome(kind, status, answer)))
        tick = max(tick + PLAN_EVERY_S, time.perf_counter())
        stop.wait(tick - time.perf_counter())
    client.close()


def plans_and_reads(url: str, name: str, start: Sequence[float], goal: Sequence[float], robot_at: Any,
                    ready: Any, stop: Any, conn: Any) -> None:
    """Every ``PLAN_EVERY_S``, each on its own thread: an R3 plan from ``start`` to ``goal``, and a window read around
    ``start``, both moved along x by ``robot_at``; sends back the samples. Runs in a process of its own."""
    def moved(point: Sequence[float]) -> list[float]:
        return [point[0] + float(robot_at.value), *point[1:]]

    def plan() -> tuple[str, str, bytes]:
        body = {"start": moved(start), "goal": moved(goal), **PLAN}
        return "POST", f"/maps/{name}/plan", json.dumps(body).encode()

    def read() -> tuple[str, str, None]:
        at = moved(start)
        lo = ",".join(str(v - h) for v, h in zip(at, READ_HALF_M))
        hi = ",".join(str(v + h) for v, h in zip(at, READ_HALF_M))
        return "GET", f"/maps/{name}/risk.npy?min={lo}&max={hi}", None

    samples: list[Sample] = []
    threads = [threading.Thread(target=_every_second, args=(url, kind, request, stop, samples))
               for kind, request in (("plan", plan), ("read", read))]
    for t in threads:
        t.start()
    ready.set()
    for t in threads:
        t.join()
    conn.send(samples)
    conn.close()


class Planner:
    """:func:`plans_and_reads` in a process of its own (the stream's threads must not share its GIL)."""

    def __init__(self, url: str, name: str, start: Sequence[float], goal: Sequence[float], robot_at: Any) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._stop, ready = ctx.Event(), ctx.Event()
        self._recv, send = ctx.Pipe(duplex=False)
        self.process = ctx.Process(target=plans_and_reads, args=(url, name, list(start), list(goal), robot_at,
                                                                 ready, self._stop, send), daemon=True)
        self.process.start()
        self.cpu = psutil.Process(self.process.pid)
        if not ready.wait(120.0):  # its imports done: its first plan leaves now
            self.process.kill()
            raise RuntimeError("the plan-and-read client did not start within 120 s")

    def stop(self) -> list[Sample]:
        self._stop.set()
        samples = self._recv.recv()
        self.process.join(timeout=30)
        return list(samples)


@dataclass(frozen=True)
class Latency:
    """The p99 of a window's answered requests (200), their count, the others', and what each answered (a plan's
    status, a refusal's HTTP status and code)."""

    p99_s: float
    n: int
    failed: int
    outcomes: dict[str, int]

    def __str__(self) -> str:
        said = "".join(f", {n} {outcome}" for outcome, n in sorted(self.outcomes.items()))
        p99 = f"{1e3 * self.p99_s:.0f} ms" if self.n else "none answered"
        return f"{p99} (n={self.n}{said})"


def latency(samples: Sequence[Sample], kind: str, start: float, end: float) -> Latency:
    inside = [(s, status, outcome) for t, k, s, status, outcome in samples if k == kind and start <= t < end]
    ok = [s for s, status, _ in inside if status == 200]
    outcomes: dict[str, int] = {}
    for _, status, outcome in inside:
        if outcome:
            outcomes[outcome] = outcomes.get(outcome, 0) + 1
    return Latency(percentile(ok, 99), len(ok), len(inside) - len(ok), outcomes)


# ---------------------------------------------------------------- CPU


@dataclass(frozen=True)
class CpuSample:
    main: float  # the server's main thread: the event loop
    threads: dict[int, float]  # its other threads by id: the pools (fusion, parsing, reads, storage)
    children: dict[int, float]  # its child processes by pid: planner workers, the JSON parser
    bench: float  # this process: the stream
    planner: float  # the plan-and-read client


def cpu_sample(server: psutil.Process, planner: psutil.Process) -> CpuSample:
    threads = {t.id: t.user_time + t.system_time for t in server.threads()}
    children = {}
    for child in server.children(recursive=True):
        try:
            times = child.cpu_times()
            children[child.pid] = times.user + times.system
        except psutil.Error:
            pass
    planner_times, own = planner.cpu_times(), psutil.Process().cpu_times()
    return CpuSample(threads.pop(server.pid, 0.0), threads, children, own.user + own.system,
                     planner_times.user + planner_times.system)


def cpu_line(before: CpuSample, after: CpuSample, seconds: float) -> str:
    pool = sorted((after.threads[t] - before.threads.get(t, 0.0) for t in after.threads), reverse=True)
    busiest = ", ".join(f"{s:.1f}" for s in pool[:4])
    parts = [("server event loop", after.main - before.main), ("server pool threads", sum(pool)),
             ("server children (planner workers, parser)",
              sum(t - before.children.get(pid, 0.0) for pid, t in after.children.items())),
             ("stream client", after.bench - before.bench), ("plan-and-read client", after.planner - before.planner)]
    ended = len(set(before.children) - set(after.children))
    total = sum(s for _, s in parts)
    cores = os.cpu_count() or 1
    return (f"CPU s over the stream's {seconds:.0f} s ({cores} cores = {cores * seconds:.0f} CPU s): "
            + ", ".join(f"{n} {s:.1f}" for n, s in parts) + f" (busiest pool threads {busiest}"
            + (f"; {ended} child process(es) ended meanwhile, their seconds not counted" if ended else "") + "); these "
            f"{total:.1f} s = {100 * total / (cores * seconds):.0f} % of the machine; load average "
            f"{os.getloadavg()[0]:.1f}")


# ---------------------------------------------------------------- one case


@dataclass
class CaseReport:
    """Every figure of one case."""

    case: str
    kind: str
    resolution: float
    clouds: int  # acknowledged in the stream
    rays: int
    seconds: float
    post_p50_s: float
    post_p99_s: float
    retries: int
    unloaded: dict[str, Latency]
    loaded: dict[str, Latency]
    in_process_clouds: int
    in_process_rays: int
    in_process_s: float
    in_process_cpu_s: float
    octomap_clouds: int
    octomap_rays: int
    octomap_s: float
    same_map: bool
    held_cells: int
    cpu: str
    server_ms: dict[str, float]  # the service's own means during the stream (bench load's /metrics histograms)

    @property
    def clouds_s(self) -> float:
        return self.clouds / self.seconds

    @property
    def rays_s(self) -> float:
        return self.rays / self.seconds

    @property
    def in_process_rays_s(self) -> float:
        return self.in_process_rays / self.in_process_s

    @property
    def octomap_rays_s(self) -> float:
        return self.octomap_rays / self.octomap_s

    def ratio(self, kind: str) -> float:
        """Loaded p99 over unloaded; NaN where either window had no answer."""
        loaded, unloaded = self.loaded[kind], self.unloaded[kind]
        return loaded.p99_s / unloaded.p99_s if loaded.n and unloaded.n else math.nan


def _x(ratio: float) -> str:
    return f"{ratio:.1f}x" if math.isfinite(ratio) else "- (none answered)"


def _call(client: LeanClient, method: str, target: str, body: dict[str, Any] | None = None,
          ok: int = 200) -> bytes:
    status, answer = client.send(method, target, None if body is None else json.dumps(body).encode())
    if status != ok:
        raise RuntimeError(f"{method} {target}: {status} {answer[:300]!r}")
    return answer


def same_cells(url: str, name: str, m: FuzzyMap) -> bool:
    """Whether the service's map holds ``m``'s cells: its bounds, risk and observed mask (``risk.npy``)."""
    bounds = m.bounds()
    with httpx.Client(base_url=url, timeout=600.0) as client:
        risk = client.get(f"/maps/{name}/risk.npy")
        observed = client.get(f"/maps/{name}/risk.npy", params={"layer": "observed"})
    if bounds is None or risk.status_code != 200 or observed.status_code != 200:
        return False
    origin = tuple(float(v) for v in risk.headers["x-map-origin"].split(","))
    return (np.allclose(origin, bounds.origin, rtol=0.0, atol=1e-9)
            and np.array_equal(npy_array(risk), m.risk()) and np.array_equal(npy_array(observed), m.observed()))


def run_case(server: ServerProcess, case: str, src: Source, resolution: float, *, seconds: float,
             unloaded_s: float, in_process_s: float, octomap_s: float) -> CaseReport:
    """Steps 1-4 of the module doc for one case; its map is deleted at the end."""
    name = f"lidar-{src.kind}-{round(resolution * 1000)}mm"
    prime = PRIME[src.kind]
    robot_at = multiprocessing.get_context("spawn").Value("d", 0.0)
    start, goal = src.position(0), src.position(1)
    # a connection each step: the service closes one left idle (FUZZYRISK_HEADER_TIMEOUT_S)
    with LeanClient(server.url, timeout=600.0) as client:
        _call(client, "POST", "/maps", map_request(name, resolution, src.forget_beyond), ok=201)
        warm = Stream(server.url, name, src, 0)
        for k in range(prime):  # the map to plan on before the stream; compiles what the server has not yet
            warm.post(client, k)
        # the worker's first plan on this map (whatever it answers): the unloaded window starts warm
        client.send("POST", f"/maps/{name}/plan", json.dumps({"start": start, "goal": goal, **PLAN}).encode())
    planner = Planner(server.url, name, start, goal, robot_at)
    try:
        quiet = (time.time(), time.time() + unloaded_s)
        time.sleep(unloaded_s)
        stream = Stream(server.url, name, src, prime, robot_at)
        process = psutil.Process(server.pid)
        scraped, before, loaded_from = scrape(server), cpu_sample(process, planner.cpu), time.time()
        began, ended = stream.run(seconds)
        after, loaded = cpu_sample(process, planner.cpu), (loaded_from, time.time())
        server_ms = mean_ms(scrape(server), scraped)
    finally:
        samples = planner.stop()
    acks = stream.check(prime)
    with LeanClient(server.url, timeout=600.0) as client:
        info = json.loads(_call(client, "GET", f"/maps/{name}"))
    if info["scans_fused"] != prime + len(acks):
        raise RuntimeError(f"{name}: {info['scans_fused']} scans fused, {prime + len(acks)} acknowledged")
    rays = sum(src.rays(a.k) for a in acks)
    latencies = [a.latency for a in acks]
    report = CaseReport(
        case=case, kind=src.kind, resolution=resolution, clouds=len(acks), rays=rays, seconds=ended - began,
        post_p50_s=percentile(latencies, 50), post_p99_s=percentile(latencies, 99),
        retries=sum(a.retries for a in acks),
        unloaded={k: latency(samples, k, *quiet) for k in ("plan", "read")},
        loaded={k: latency(samples, k, *loaded) for k in ("plan", "read")},
        in_process_clouds=0, in_process_rays=0, in_process_s=math.nan, in_process_cpu_s=math.nan,
        octomap_clouds=0, octomap_rays=0, octomap_s=math.nan, same_map=False, held_cells=int(info["held_cells"]),
        cpu=cpu_line(before, after, ended - began), server_ms=server_ms)
    in_process(report, src, resolution, [k for k in range(prime)], [a.k for a in acks], in_process_s, server.url,
               name)
    octomap(report, src, resolution, [a.k for a in acks], octomap_s)
    with LeanClient(server.url) as client:
        _call(client, "DELETE", f"/maps/{name}", ok=204)
    return report


def in_process(report: CaseReport, src: Source, resolution: float, primed: list[int], streamed: list[int],
               budget_s: float, url: str, name: str) -> None:
    """Step 3: the primed clouds untimed, then the streamed ones in the service's order, timed for ``budget_s`` (a
    cloud at least), then the rest untimed; the two maps compared."""
    m = growing_map(resolution, src.forget_beyond)
    for k in primed:
        m.integrate_batch([src.cloud(k)])
    wall = cpu = 0.0
    done = rays = 0
    for k in streamed:
        cloud = src.cloud(k)
        if done and wall >= budget_s:  # past the budget: fused for the comparison only
            m.integrate_batch([cloud])
            continue
        with Clock() as clock:
            m.integrate_batch([cloud])
        wall, cpu, done, rays = wall + clock.wall, cpu + clock.cpu, done + 1, rays + src.rays(k)
    report.in_process_clouds, report.in_process_rays = done, rays
    report.in_process_s, report.in_process_cpu_s = wall, cpu
    report.same_map = same_cells(url, name, m)


def octomap(report: CaseReport, src: Source, resolution: float, streamed: list[int], budget_s: float) -> None:
    """Step 4: OctoMap on the streamed clouds, in the same order, until ``budget_s`` (one cloud at least)."""
    import octomap as octo  # the bench extra: octomap-python

    tree = octo.OcTree(resolution)
    wall = 0.0
    done = rays = 0
    for k in streamed:
        if done and wall >= budget_s:
            break
        cloud = src.cloud(k)
        points, origin = np.ascontiguousarray(cloud.points), np.asarray(cloud.origin, dtype=np.float64)
        with Clock() as clock:
            tree.insertPointCloud(points, origin, maxrange=cloud.range_max)
        wall, done, rays = wall + clock.wall, done + 1, rays + src.rays(k)
    report.octomap_clouds, report.octomap_rays, report.octomap_s = done, rays, wall


# ---------------------------------------------------------------- printing


def case_lines(r: CaseReport) -> list[str]:
    same = "yes" if r.same_map else "**NO**"
    return [
        f"### {r.case}: {r.kind} clouds at {r.resolution:g} m",
        f"over HTTP: {r.clouds} clouds acknowledged of {r.clouds} sent, {r.rays:,} rays in {r.seconds:.1f} s: "
        f"**{r.clouds_s:.2f} clouds/s, {r.rays_s / 1e6:.3f} M rays/s**; post latency p50 {1e3 * r.post_p50_s:.0f} ms, "
        f"p99 {1e3 * r.post_p99_s:.0f} ms; {r.retries} retries after a 503; the map holds {r.held_cells:,} cells",
        f"in-process integrate_batch: {r.in_process_clouds} clouds timed in {r.in_process_s:.1f} s "
        f"({r.in_process_cpu_s:.1f} CPU s): {r.in_process_clouds / r.in_process_s:.2f} clouds/s, "
        f"{r.in_process_rays_s / 1e6:.3f} M rays/s; HTTP / in-process {r.rays_s / r.in_process_rays_s:.2f}x; "
        f"the service's map the in-process one, cell for cell: {same}",
        f"OctoMap insertPointCloud: {r.octomap_clouds} clouds in {r.octomap_s:.1f} s: "
        f"{r.octomap_rays_s / 1e6:.3f} M points/s; in-process / OctoMap "
        f"**{r.in_process_rays_s / r.octomap_rays_s:.1f}x**",
        f"plan p99 {r.loaded['plan']} loaded against {r.unloaded['plan']} unloaded (**{_x(r.ratio('plan'))}**); "
        f"read p99 {r.loaded['read']} against {r.unloaded['read']} (**{_x(r.ratio('read'))}**)",
        f"the service's own means during the stream (/metrics): a scan request {r.server_ms['scan_requests']:.0f} ms, "
        f"of which its commit {r.server_ms['commit']:.0f} ms and its fusion {r.server_ms['fusion']:.0f} ms; a plan "
        f"{r.server_ms['plans']:.0f} ms",
        r.cpu,
    ]


def summary_table(reports: Sequence[CaseReport]) -> str:
    lines = ["| case | clouds/s HTTP | M rays/s HTTP | in-process | OctoMap | in-process / OctoMap | "
             "HTTP / in-process | "
             "post p50 / p99 ms | plan p99 x unloaded | read p99 x unloaded |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in reports:
        lines.append(
            f"| {r.case} | {r.clouds_s:.2f} | {r.rays_s / 1e6:.3f} | {r.in_process_rays_s / 1e6:.3f} | "
            f"{r.octomap_rays_s / 1e6:.3f} | {r.in_process_rays_s / r.octomap_rays_s:.1f}x | "
            f"{r.rays_s / r.in_process_rays_s:.2f}x | {1e3 * r.post_p50_s:.0f} / {1e3 * r.post_p99_s:.0f} | "
            f"{_x(r.ratio('plan'))} | {_x(r.ratio('read'))} |")
    return "\n".join(lines)


def targets(reports: Sequence[CaseReport]) -> list[tuple[str, bool | None]]:
    """Each target and whether it is met (None: no case of this run measures it)."""
    def where(kind: str, resolution: float) -> list[CaseReport]:
        return [r for r in reports if r.kind == kind and r.resolution == resolution]

    ouster, os1 = where("ouster", 0.1), where("os1-128", 0.1)
    ratios = [r.ratio(k) for r in reports for k in ("plan", "read")]
    return [
        (f"Ouster frames at 0.1 m over HTTP >= {TARGET_OUSTER_CLOUDS_S:g} frames/s "
         f"({', '.join(f'{r.clouds_s:.2f}' for r in ouster) or 'not run'})",
         all(r.clouds_s >= TARGET_OUSTER_CLOUDS_S for r in ouster) if ouster else None),
        (f"synthetic OS1-128 at 0.1 m over HTTP >= {TARGET_OS1_128_RAYS_S / 1e6:g} M rays/s "
         f"({', '.join(f'{r.rays_s / 1e6:.3f}' for r in os1) or 'not run'})",
         all(r.rays_s >= TARGET_OS1_128_RAYS_S for r in os1) if os1 else None),
        (f"post p99 <= {1e3 * TARGET_POST_P99_S:.0f} ms (worst {1e3 * max(r.post_p99_s for r in reports):.0f} ms)",
         all(r.post_p99_s <= TARGET_POST_P99_S for r in reports)),
        (f"plan and read p99 within {TARGET_LOADED_X:g}x of unloaded (worst "
         f"{_x(max((x for x in ratios if math.isfinite(x)), default=math.nan))}; a case with no answer "
         "in a window misses it; refusals are listed with each case)",
         all(x <= TARGET_LOADED_X for x in ratios)),
        (f"in-process fusion >= {TARGET_VS_OCTOMAP:g}x OctoMap's points/s (least "
         f"{min(r.in_process_rays_s / r.octomap_rays_s for r in reports):.1f}x)",
         all(r.in_process_rays_s / r.octomap_rays_s >= TARGET_VS_OCTOMAP for r in reports)),
    ]


def targets_line(reports: Sequence[CaseReport]) -> str:
    verdict = {True: "met", False: "**NOT met**", None: "not measured"}
    return "targets: " + "; ".join(f"{name}: {verdict[ok]}" for name, ok in targets(reports))


# ---------------------------------------------------------------- the command


def parse_cases(text: str) -> list[tuple[str, str, float]]:
    """``kind@resolution`` items, comma-separated: ``(case, kind, resolution)``; ``ValueError`` naming a bad one."""
    out = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        kind, _, res = item.partition("@")
        if kind not in PRIME or not res:
            raise ValueError(f"{item!r}: a case is KIND@RESOLUTION, KIND one of {', '.join(PRIME)}")
        out.append((item, kind, float(res)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench lidar", description=__doc__.split("\n\n")[0])
    _data.add_option(ap)
    ap.add_argument("--quick", action="store_true", help=f"{', '.join(QUICK_CASES)}, {QUICK_SECONDS:g} s streams, "
                    f"{QUICK_SYNTHETIC_SWEEPS} synthetic sweeps, one OctoMap cloud (a test-sized run)")
    ap.add_argument("--seconds", type=float,
                    help=f"each stream's seconds (default {SECONDS:g}, --quick {QUICK_SECONDS:g})")
    ap.add_argument("--cases", help=f"comma-separated KIND@RESOLUTION (default {','.join(CASES)})")
    ap.add_argument("--in-process-seconds", type=float, default=IN_PROCESS_S,
                    help="seconds of in-process fusion timed a case (every cloud with --quick); the rest are fused "
                    "untimed, for the comparison of the maps")
    ap.add_argument("--octomap-seconds", type=float, default=OCTOMAP_S,
                    help="OctoMap fuses clouds until this many seconds passed (one cloud with --quick)")
    args = ap.parse_args(argv)
    _data.use(args)
    try:
        cases = parse_cases(args.cases or ",".join(QUICK_CASES if args.quick else CASES))
    except ValueError as exc:
        ap.error(f"--cases: {exc}")
    seconds = args.seconds if args.seconds is not None else QUICK_SECONDS if args.quick else SECONDS
    if not seconds > 0:
        ap.error(f"--seconds must be positive, got {seconds}")
    unloaded_s = QUICK_UNLOADED_S if args.quick else UNLOADED_S
    in_process_s = math.inf if args.quick else args.in_process_seconds
    octomap_s = 0.0 if args.quick else args.octomap_seconds

    began = time.perf_counter()
    print(f"# bench lidar, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(f"machine: {machine()}")
    print(f"cases: {', '.join(c for c, _, _ in cases)}; streams of {seconds:g} s, {IN_FLIGHT} clouds in flight; "
          f"plan and read every {PLAN_EVERY_S:g} s, {unloaded_s:g} s unloaded first; {_data.describe()}", flush=True)
    sources: dict[str, Source] = {}
    reports: list[CaseReport] = []
    # the service's default planner warm-up: a first plan must not time the worker's start and compilation
    with ServerProcess(env={"FUZZYRISK_PLAN_WARMUP": "true"}) as server:
        with httpx.Client(base_url=server.url, timeout=30.0) as client:
            wait_ready(client, 600.0)
        try:
            for case, kind, resolution in cases:
                if kind not in sources:
                    sources[kind] = source(kind, args.quick)
                src = sources[kind]
                print(f"[{time.perf_counter() - began:4.0f} s] {case}: {len(src.sweeps)} sweeps of "
                      f"{min(s.rays for s in src.sweeps):,}-{max(s.rays for s in src.sweeps):,} rays"
                      f"{f', loops {src.shift_m:g} m apart' if src.shift_m else ''}"
                      f"{f', forget_beyond {src.forget_beyond:g} m' if src.forget_beyond else ''}",
                      file=sys.stderr, flush=True)
                reports.append(run_case(server, case, src, resolution, seconds=seconds, unloaded_s=unloaded_s,
                                        in_process_s=in_process_s, octomap_s=octomap_s))
        except Exception:
            print(f"the server's log:\n{server.log_tail()}", file=sys.stderr)  # its traceback, if it was the server
            raise
    print()
    for r in reports:
        print("\n".join(case_lines(r)))
        print()
    print(summary_table(reports))
    print()
    print(targets_line(reports))
    print(f"took {time.perf_counter() - began:.0f} s; load average at the end {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
