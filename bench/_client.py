"""Shared helpers of the load, fault and soak benchmarks (and of tests/faults, tests/hostile).

* :class:`ServerProcess`: ``python -m app`` in its own process group on a free loopback
  port, with a data directory of its own (a temporary one unless given), ``kill -9`` and restart.
* :class:`Fleet`: simulated robots in one room (``bench.bench_fusion.planar_scene``: exact
  ray-box ranges, 1080 beams over 270 degrees) with their scans pre-encoded as request bodies
  (JSON batches and binary float32 uploads), and the same scans as ``fuzzyocc.LaserScan`` for
  in-process replay. Ranges are float32 values, so JSON, binary and replay fuse identical numbers.
* :class:`LeanClient`: one keep-alive HTTP/1.1 connection for a simulated robot's uploads, far
  cheaper in CPU than httpx (the load generator shares the machine with the server it measures).
* :func:`health_prober`: ``GET /health`` latencies from a separate process (the clients' own
  GIL must not be what is measured).
"""

from __future__ import annotations

import http.client
import json
import math
import multiprocessing
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlencode, urlsplit

import httpx
import numpy as np

from bench.bench_fusion import RANGE_MAX_M, RANGE_NOISE_M, planar_scene
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan, SensorModel

ROOT = Path(__file__).resolve().parents[1]
RANGE_MIN_M = 0.05


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def percentile(values: Sequence[float], q: float) -> float:
    """The q-th percentile (0..100) of ``values``; NaN when there are none."""
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else math.nan


@dataclass
class ServerProcess:
    """The service in its own process group, on loopback.

    Parameters
    ----------
    data_dir : Path or None
        Map database directory; None = one inside this server's temporary directory (which
        also holds ``server.log``), removed by :meth:`close`.
    env : dict
        Extra ``FUZZYRISK_*`` variables. Defaults here: no planner warm-up, one planner worker,
        key-value logs at WARNING (a benchmark does not want thousands of access records).
    preexec : callable or None
        Run in the child before ``exec`` (after ``setsid``), e.g. to set a resource limit.
    """

    data_dir: Path | None = None
    env: dict[str, str] = field(default_factory=dict)
    preexec: Callable[[], None] | None = None
    port: int = 0
    process: subprocess.Popen[bytes] | None = None
    log_path: Path | None = None
    _tmp: Path | None = None
    starts: int = 0

    def __post_init__(self) -> None:
        # the log lives apart from the data: a full or read-only data directory must not lose it
        self._tmp = Path(tempfile.mkdtemp(prefix="fuzzyrisk-bench-"))
        if self.data_dir is None:
            self.data_dir = self._tmp / "data"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def pid(self) -> int:
        assert self.process is not None, "server not started"
        return self.process.pid

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def start(self, timeout_s: float = 120.0, *, port: int | None = None) -> ServerProcess:
        """Start and wait for ``/health``; ``RuntimeError`` with the log tail if it exits or never answers."""
        assert not self.alive(), "already running"
        assert self.data_dir is not None
        self.port = port or free_port()
        env = {
            **os.environ,
            "FUZZYRISK_PLAN_WORKERS": "1",
            "FUZZYRISK_PLAN_WARMUP": "false",
            "FUZZYRISK_LOG_FORMAT": "kv",
            "FUZZYRISK_LOG_LEVEL": "WARNING",
            **self.env,
        }
        assert self._tmp is not None
        self.log_path = self._tmp / "server.log"
        self.starts += 1
        with self.log_path.open("ab") as log:
            log.write(f"\n==== start {self.starts} on port {self.port}\n".encode())
            log.flush()
            # own session: kill() can end the planner workers with the server, as a container's end would
            self.process = subprocess.Popen(
                [sys.executable, "-m", "app", "--port", str(self.port), "--data-dir", str(self.data_dir)],
                cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                preexec_fn=self.preexec,
            )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited with {self.process.returncode}:\n{self.log_tail()}")
            try:
                # the port was free when chosen; make sure it is our process that answers on it
                if httpx.get(f"{self.url}/health", timeout=2.0).status_code == 200 and self._listens():
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        self.kill()
        raise RuntimeError(f"server did not answer /health within {timeout_s} s:\n{self.log_tail()}")

    def _listens(self) -> bool:
        import psutil

        try:
            connections = psutil.Process(self.pid).net_connections(kind="tcp")
        except psutil.Error:
            return False
        return any(c.status == psutil.CONN_LISTEN and c.laddr.port == self.port for c in connections)

    def log_tail(self, chars: int = 4000) -> str:
        return self.log_path.read_text(errors="replace")[-chars:] if self.log_path and self.log_path.exists() else ""

    def kill(self) -> None:
        """SIGKILL the server (no flush, no snapshot), then its process group (planner workers)."""
        if self.process is None:
            return
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(timeout=30)
        try:
            os.killpg(self.process.pid, signal.SIGKILL)  # our own group only: the workers it started
        except ProcessLookupError:
            pass

    def terminate(self, timeout_s: float = 60.0) -> int:
        """SIGTERM: the graceful stop (requests in flight finish, maps are snapshotted); the exit code."""
        assert self.process is not None
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(timeout=timeout_s)
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        return code

    def close(self) -> None:
        """Stop the server if it runs, and remove its temporary directory (log, and data unless given)."""
        self.kill()
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------- simulated robots


@dataclass(frozen=True)
class Scan:
    """One planar scan: pose, beam geometry and float32 ranges (+inf = no return)."""

    pose: tuple[float, float, float]
    angle_min: float
    angle_increment: float
    ranges: np.ndarray  # float32

    def to_json(self) -> dict[str, Any]:
        # float32 -> float is exact and json writes the shortest repr that reads back to it
        values: list[Any] = ["inf" if math.isinf(r) else float(r) for r in self.ranges.tolist()]
        return {
            "pose": {"x": self.pose[0], "y": self.pose[1], "theta": self.pose[2]},
            "angle_min": self.angle_min, "angle_increment": self.angle_increment, "ranges": values,
            "range_min": RANGE_MIN_M, "range_max": RANGE_MAX_M,
        }

    def binary(self) -> tuple[bytes, dict[str, float]]:
        """Body (raw little-endian float32 ranges) and query of the binary upload."""
        params = {"x": self.pose[0], "y": self.pose[1], "theta": self.pose[2], "angle_min": self.angle_min,
                  "angle_increment": self.angle_increment, "range_min": RANGE_MIN_M, "range_max": RANGE_MAX_M}
        return self.ranges.astype("<f4").tobytes(), params

    def laser_scan(self) -> LaserScan:
        return LaserScan(pose=self.pose, angle_min=self.angle_min, angle_increment=self.angle_increment,
                         ranges=self.ranges.astype(np.float64), range_min=RANGE_MIN_M, range_max=RANGE_MAX_M)


def json_body(scans: Sequence[Scan]) -> bytes:
    """A ``ScanBatch`` request body."""
    return json.dumps({"scans": [s.to_json() for s in scans]}).encode()


@dataclass(frozen=True)
class Batch:
    """One request: its scans, and its body as JSON (``params`` None) or binary (one scan)."""

    scans: tuple[Scan, ...]
    body: bytes
    params: dict[str, float] | None

    @property
    def content_type(self) -> str:
        return "application/json" if self.params is None else "application/octet-stream"

    @property
    def kind(self) -> str:
        return "json" if self.params is None else "binary"

    def post(self, client: httpx.Client, name: str, headers: dict[str, str] | None = None) -> httpx.Response:
        return client.post(f"/maps/{name}/scans", content=self.body, params=self.params,
                           headers={"content-type": self.content_type, **(headers or {})})

    def laser_scans(self) -> list[LaserScan]:
        return [s.laser_scan() for s in self.scans]

    def target(self, name: str) -> str:
        """Path and query of this batch's upload to map ``name``."""
        return f"/maps/{name}/scans" + (f"?{urlencode(self.params)}" if self.params is not None else "")


class LeanClient:
    """One keep-alive HTTP/1.1 connection (``http.client``) that posts scan batches: a robot of the load bench.

    The load generator runs on the machine it measures, so its own CPU is taken from the server:
    a batch posted through httpx costs the client about 0.9 ms of CPU, through this about 0.2 ms
    (an idle machine, 1080-beam binary scans). Any error closes the connection; the next request
    opens a new one.
    """

    def __init__(self, base_url: str, timeout: float = 60.0) -> None:
        url = urlsplit(base_url)
        self._conn = http.client.HTTPConnection(url.hostname or "127.0.0.1", url.port or 80, timeout=timeout)

    def post(self, name: str, batch: Batch) -> int:
        """POST the batch to map ``name``; the status code (``OSError`` / ``HTTPException`` on a broken connection)."""
        return self.send("POST", batch.target(name), batch.body, batch.content_type)[0]

    def send(self, method: str, target: str, body: bytes | None = None,
             content_type: str = "application/json") -> tuple[int, bytes]:
        """One request (``target``: path and query); the status code and the answer's body."""
        try:
            self._conn.request(method, target, body=body, headers={"Content-Type": content_type} if body else {})
            response = self._conn.getresponse()
            return response.status, response.read()
        except (OSError, http.client.HTTPException):
            self._conn.close()
            raise

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> LeanClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_batch(scans: Sequence[Scan], binary: bool) -> Batch:
    if binary:
        assert len(scans) == 1, "the binary upload carries one scan"
        body, params = scans[0].binary()
        return Batch(tuple(scans), body, params)
    return Batch(tuple(scans), json_body(scans), None)


@dataclass
class Fleet:
    """Robots scanning one room: ``scans[r]`` are robot r's scans, in the order it takes them."""

    spec: GridSpec
    scans: list[list[Scan]]
    free_points: np.ndarray  # (K, 2) sensor positions: free space, good plan endpoints

    @classmethod
    def generate(cls, robots: int, scans_per_robot: int, seed: int = 5, beams: int = 1080) -> Fleet:
        scene = planar_scene(np.random.default_rng(seed), robots * scans_per_robot, beams=beams)
        assert scene.angles is not None
        angle_min, increment = scene.angles
        flat = [
            Scan(pose=(float(o[0]), float(o[1]), float(o[2])), angle_min=float(angle_min),
                 angle_increment=float(increment), ranges=r.astype(np.float32))
            for o, r in zip(scene.origins, scene.ranges)
        ]
        per_robot = [flat[i::robots] for i in range(robots)]
        return cls(scene.spec, per_robot, np.array([o[:2] for o in scene.origins]))

    def map_request(self, name: str, model: str = "fuzzy") -> dict[str, Any]:
        """POST /maps body for a map the size of the room."""
        return {"name": name, "dimensions": 2, "resolution": self.spec.resolution, "origin": list(self.spec.origin),
                "size": list(self.spec.size), "model": model, "sensor": {"range_sigma": RANGE_NOISE_M}}

    def batches(self, robot: int, batch_size: int, binary: bool) -> list[Batch]:
        """Robot ``robot``'s scans cut into requests (binary: one scan each)."""
        scans = self.scans[robot]
        size = 1 if binary else batch_size
        return [make_batch(scans[i:i + size], binary) for i in range(0, len(scans) - size + 1, size)]


def new_map(spec: GridSpec, model: str = "fuzzy") -> FuzzyMap | BayesMap:
    """An in-process map as the service builds it from :meth:`Fleet.map_request`."""
    sensor = SensorModel(range_sigma=RANGE_NOISE_M)
    return FuzzyMap(spec, sensor) if model == "fuzzy" else BayesMap(spec, sensor)


def npy_array(response: httpx.Response) -> np.ndarray:
    import io

    return np.load(io.BytesIO(response.content), allow_pickle=False)


# ---------------------------------------------------------------- /health from another process


def _probe(url: str, interval_s: float, stop: Any, conn: Any) -> None:
    latencies: list[tuple[float, float]] = []
    failures = 0
    with httpx.Client(timeout=5.0) as client:
        while not stop.is_set():
            t0 = time.perf_counter()
            try:
                ok = client.get(url).status_code == 200
            except httpx.HTTPError:
                ok = False
            dt = time.perf_counter() - t0
            if ok:
                latencies.append((time.time(), dt))
            else:
                failures += 1
            time.sleep(max(0.0, interval_s - dt))
    conn.send((latencies, failures))
    conn.close()


class HealthProber:
    """``GET /health`` every ``interval_s`` from a separate process; :meth:`stop` returns the samples.

    Samples are (wall time, latency seconds); ``failures`` counts non-200 answers and errors.
    """

    def __init__(self, base_url: str, interval_s: float = 0.02) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        self._recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_probe, args=(f"{base_url}/health", interval_s, self._stop, send), daemon=True)
        self._proc.start()

    def stop(self) -> tuple[list[tuple[float, float]], int]:
        self._stop.set()
        latencies, failures = self._recv.recv()
        self._proc.join(timeout=10)
        return latencies, failures


def window(samples: Sequence[tuple[float, float]], start: float, end: float) -> list[float]:
    """The values of (time, value) samples taken in [start, end)."""
    return [v for t, v in samples if start <= t < end]


def machine() -> str:
    """One line: cores, CPU model, RAM, load average."""
    model = "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import psutil

    ram = psutil.virtual_memory().total / 2**30
    return f"{os.cpu_count()} cores, {model}, {ram:.1f} GiB RAM, load average {os.getloadavg()[0]:.1f}"


def wait_ready(client: httpx.Client, timeout_s: float) -> None:
    """Until ``GET /ready`` answers 200 (maps loaded, kernels compiled, planner workers up); ``RuntimeError`` after
    ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if client.get("/ready").status_code == 200:
            return
        time.sleep(0.2)
    raise RuntimeError(f"the service was not ready within {timeout_s} s")


def chunks(seq: Sequence[Any], size: int) -> Iterator[Sequence[Any]]:
    for i in range(0, len(seq), size):
        yield seq[i:i + size]
