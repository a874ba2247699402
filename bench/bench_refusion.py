"""Re-fusion after a loop closure, through the service: a drifted map rebuilt at corrected poses.

    python3 dev.py bench refusion [--quick] [--logs a,b] [--data DIR] [--window S]
    python -m bench.bench_refusion ...                                 (from the repository root)

The shared CARMEN logs carry only corrected poses (their odometry fields repeat them), so the drift a
SLAM loop closure corrects is simulated (:func:`drift_poses`): odometry-like, a seeded random walk
composed along the log, each step of length ``d`` between two scans adding a Gaussian error of 2 % of
``d`` to each axis of its motion (in the robot's frame) and of 1 degree times ``d`` (in metres) to its
turn. One ``python -m app`` on loopback (``bench._client.ServerProcess``), 0.05 m cells, the box of the
log's corrected poses and hits (``bench maps``' box). For each log (``--logs``, default every log of
``DIR/carmen``):

1. fuse 9 scans of every 10 (``bench/_logmaps.py``: the 10th are held out) over HTTP as
   ``python -m app.import_log --url`` posts them (``app.cli``'s client and ``scan_json``: JSON batches of
   32, each scan's stamp as ``header.stamp``, ``fuzzyocc.carmen.log_stamps_ns``): the drifted scans into
   map A, the corrected ones into map B;
2. PUT the corrected sensor poses to A as a ``nav_msgs/Path`` (:func:`sensor_path`: every scan's
   stamp, a yaw quaternion) and poll ``GET /maps/A/rebuild`` until that correction is done;
3. print the held-out beam quality (``bench maps``' metric) of A drifted, A rebuilt and B, whether A's
   and B's ``risk.npy`` are identical (bit for bit), the rebuild's time (the status's ``elapsed_s``: the
   job's, from the correction stored to the switch, on the service's clock; and PUT to done on ours, which
   also counts the PUT's own answer and our polls, whose sleeps overshoot the end by up to half the
   status's ``eta_s``) and its scans/s by ``elapsed_s`` beside ``FuzzyMap.integrate_batch`` of the same
   scans in this process, each rebuild followed by one, by the wall clock and by CPU (the server process's
   CPU seconds from the PUT to done against ours; target >= 0.9x), each side the median of ``REPEATS``
   runs (the same corrected path PUT again rebuilds the whole history again), and its speed as a multiple
   of the log's duration (its last stamp less its first; target >= 100x where the stamps are real: a log
   whose stamps do not increase is numbered at 5 Hz, and its row says so and is not judged).

Then, on the log with the most scans: an innocent client (``bench._abuse_clients.Innocent``, its own
process) posts a binary 1080-beam scan every 0.1 s to a map of its own and reads its ``risk.npy``
every 0.1 s, unloaded for ``--window`` seconds, then while A is rebuilt again and again (the drifted
and the corrected poses in turn, each PUT once the last rebuild is done, until ``--window`` has
passed and the corrected poses were the last), then unloaded for half ``--window``: its p99 during the
rebuilds against unloaded, the two quiet windows pooled (target <= 2x). ``--quick``: orebro and seattle
(478 scans), 10 s windows.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import os
import sys
import time
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

import httpx
import numpy as np
import psutil

from app.cli import trajectory
from app.cli.common import ServiceClient, create_map
from app.cli.import_log import scan_json
from bench import _data, _logmaps
from bench._abuse_clients import Innocent, InnocentSetup
from bench._client import Fleet, ServerProcess, chunks, machine, wait_ready
from bench.bench_abuse import innocent_latency, ms
from bench.bench_maps import _warm_up
from fuzzyocc import FuzzyMap, GridSpec, LaserScan, SensorModel
from fuzzyocc.carmen import read_carmen
from fuzzyocc.presets import DEFAULT_PRESET

#: Odometry's error per metre travelled: of position (each axis of a step's motion) and of heading.
DRIFT_POSITION_PER_M = 0.02
DRIFT_HEADING_RAD_PER_M = math.radians(1.0)
_Run = TypeVar("_Run", bound=tuple[Any, ...])
SEED = 20261207
BATCH = 32  # scans a request, as python -m app.import_log posts them (its --batch default)
FRAME = "map"
QUICK_LOGS = ("orebro", "seattle")
WINDOW_S = 30.0  # the innocent's unloaded window, and the least its loaded one lasts
QUICK_WINDOW_S = 10.0
#: GET .../rebuild while a timed rebuild runs: half its eta_s, within these seconds (few polls, whose CPU the
#: server's counts as the rebuild's, and the end seen within 20 ms)
POLL_S = (0.02, 1.0)
POLL_LOADED_S = (0.2, 1.0)  # ... while the innocent is measured (our polling is not its load)
REBUILD_TIMEOUT_S = 600.0
TARGET_RATE = 0.9  # the rebuild's scans/s, at least this share of in-process fusion's
TARGET_SPEED = 100.0  # the rebuild, at least this many times faster than the log was recorded
TARGET_P99 = 2.0  # the innocent's p99 during rebuilds, at most this multiple of unloaded
#: rebuilds and in-process fusions timed a log, each side's median kept: one run of either moved by 10-50 % between
#: two runs of the same log (other work on the machine, the heap's state)
REPEATS = 5


# ---------------------------------------------------------------- the drift


def drift_poses(poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``poses`` (N, 3: x, y, theta) as odometry would have them: each step's motion in the robot's frame and its
    turn, plus Gaussian errors of ``DRIFT_POSITION_PER_M`` and ``DRIFT_HEADING_RAD_PER_M`` times the step's length,
    composed from the first pose (which is kept). Headings wrapped to [-pi, pi]."""
    poses = np.asarray(poses, dtype=np.float64)
    step = np.diff(poses[:, :2], axis=0)
    length = np.hypot(step[:, 0], step[:, 1])
    c, s = np.cos(poses[:-1, 2]), np.sin(poses[:-1, 2])
    forward = c * step[:, 0] + s * step[:, 1]  # the step in the frame of the pose it starts from
    left = -s * step[:, 0] + c * step[:, 1]
    turn = np.angle(np.exp(1j * np.diff(poses[:, 2])))
    forward = forward + rng.normal(0.0, 1.0, length.size) * DRIFT_POSITION_PER_M * length
    left = left + rng.normal(0.0, 1.0, length.size) * DRIFT_POSITION_PER_M * length
    turn = turn + rng.normal(0.0, 1.0, length.size) * DRIFT_HEADING_RAD_PER_M * length
    heading = poses[0, 2] + np.concatenate([[0.0], np.cumsum(turn)])
    hc, hs = np.cos(heading[:-1]), np.sin(heading[:-1])
    moves = np.stack([hc * forward - hs * left, hs * forward + hc * left], axis=1)
    out = np.empty_like(poses)
    out[:, :2] = poses[0, :2] + np.concatenate([np.zeros((1, 2)), np.cumsum(moves, axis=0)])
    out[:, 2] = np.angle(np.exp(1j * heading))
    out[0] = poses[0]
    return out


@dataclass(frozen=True)
class Drift:
    """A log's scans at drifted poses, and how far the drift took them from the corrected ones."""

    scans: list[LaserScan]
    travelled_m: float
    end_m: float  # position error at the last scan
    worst_m: float
    worst_heading_rad: float


def drifted(scans: Sequence[LaserScan], seed: int) -> Drift:
    """The scans at poses drifted by :func:`drift_poses` (``seed`` makes the walk), beams and stamps kept."""
    poses = np.array([s.pose for s in scans], dtype=np.float64)
    walked = drift_poses(poses, np.random.default_rng(seed))
    error = np.hypot(*(walked[:, :2] - poses[:, :2]).T)
    heading = np.abs(np.angle(np.exp(1j * (walked[:, 2] - poses[:, 2]))))
    moved = [dataclasses.replace(s, pose=(float(x), float(y), float(t))) for s, (x, y, t) in zip(scans, walked)]
    return Drift(moved, float(np.hypot(*np.diff(poses[:, :2], axis=0).T).sum()), float(error[-1]),
                 float(error.max()), float(heading.max()))


def log_seed(name: str) -> int:
    """The drift's seed of a log: the same walk on every run, another one for each log."""
    return SEED + zlib.crc32(name.encode())


# ---------------------------------------------------------------- the corrected trajectory


def sensor_path(scans: Sequence[LaserScan]) -> dict[str, Any]:
    """``nav_msgs/Path`` JSON of the scans' sensor poses at their stamps, as a SLAM node publishes a corrected
    trajectory and as ``GET /maps/{name}/trajectory`` gives a map's (``app.cli.trajectory.sensor_path``, what
    ``python -m app.import_log --trajectory`` puts)."""
    return trajectory.sensor_path([s.pose for s in scans], [s.stamp_ns or 0 for s in scans], FRAME)


# ---------------------------------------------------------------- the service


class Refusion:
    """This bench's calls to the service, through the importer's client (``app.cli.common.ServiceClient``), and the
    CPU seconds the server has used."""

    def __init__(self, server: ServerProcess) -> None:
        self.client = ServiceClient(server.url, None)
        self._process = psutil.Process(server.pid)

    def cpu_s(self) -> float:
        """The server process's CPU seconds so far, every thread's (its planner workers apart)."""
        times = self._process.cpu_times()
        return float(times.user + times.system)

    def create(self, name: str, spec: GridSpec) -> None:
        """The map as ``python -m app.import_log --url`` creates it (the in-process sensor model, stated)."""
        create_map(self.client, argparse.Namespace(map=name, resolution=spec.resolution, model="fuzzy"), spec)

    def post(self, name: str, scans: Sequence[LaserScan]) -> float:
        """Post the scans in order, ``BATCH`` a request; seconds from the first request to the last answer."""
        started = time.perf_counter()
        for batch in chunks(scans, BATCH):
            self.client.call("POST", f"/maps/{name}/scans", json.dumps({"scans": [scan_json(s) for s in batch]}).encode())
        return time.perf_counter() - started

    def risk(self, name: str) -> np.ndarray:
        return np.load(io.BytesIO(self.client.call("GET", f"/maps/{name}/risk.npy")[1]), allow_pickle=False)

    def correct(self, name: str, path: dict[str, Any]) -> dict[str, Any]:
        """PUT the trajectory; the RebuildStatus of the 202."""
        return trajectory.put_trajectory(self.client, name, path)

    def wait(self, name: str, rebuild_id: str, poll_s: tuple[float, float] = POLL_S) -> dict[str, Any]:
        """Poll the map's rebuild until the correction ``rebuild_id`` is done (or failed): its last status. The next
        poll comes after half the rebuild's ``eta_s``, within ``poll_s`` (least, most): the importer's
        ``wait_for_rebuild`` polls every 0.5 s, too coarse a clock for a rebuild of half a second."""
        deadline = time.monotonic() + REBUILD_TIMEOUT_S
        while time.monotonic() < deadline:
            status = dict(json.loads(self.client.call("GET", f"/maps/{name}/rebuild")[1]))
            if status["id"] == rebuild_id and status["state"] in ("done", "failed"):
                return status
            eta = status.get("eta_s") if status["id"] == rebuild_id else None
            time.sleep(min(max(eta / 2 if eta is not None else poll_s[0], poll_s[0]), poll_s[1]))
        raise RuntimeError(f"{name}: rebuild {rebuild_id} not done within {REBUILD_TIMEOUT_S:g} s")

    def delete(self, name: str) -> None:
        self.client.call("DELETE", f"/maps/{name}", ok=(204,))


# ---------------------------------------------------------------- one log


@dataclass
class LogReport:
    """Every figure of one log."""

    name: str
    scans: int
    fused: int
    shape: tuple[int, ...]
    drift: Drift
    duration_s: float
    numbered: bool
    drifted: _logmaps.Score
    rebuilt: _logmaps.Score
    direct: _logmaps.Score
    identical: bool
    status: dict[str, Any]  # the median rebuild's
    put_to_done_s: float
    rebuild_cpu_s: float  # the server's, PUT to done: the rebuild's and the answers to our polls (median)
    in_process_s: float  # medians
    in_process_cpu_s: float
    path: dict[str, Any]
    drifted_path: dict[str, Any]

    @property
    def rebuild_s(self) -> float:
        """The rebuild job's seconds, correction stored to switch, as the service timed it."""
        return float(self.status["elapsed_s"])

    @property
    def rebuild_rate(self) -> float:
        return self.status["scans_total"] / self.rebuild_s

    @property
    def in_process_rate(self) -> float:
        return self.fused / self.in_process_s

    @property
    def rate_ratio(self) -> float:
        return self.rebuild_rate / self.in_process_rate

    @property
    def cpu_ratio(self) -> float:
        """In-process fusion's CPU seconds over the server's during the rebuild: the rate ratio by CPU."""
        return self.in_process_cpu_s / self.rebuild_cpu_s

    @property
    def speed(self) -> float:
        return self.duration_s / self.rebuild_s


def run_log(service: Refusion, path: Path) -> LogReport:
    """Drift, fuse, correct and compare one log (module doc, steps 1-3); its maps ``NAME-a``, ``NAME-b`` are kept."""
    name = _logmaps.log_name(path)
    said: list[str] = []
    scans = read_carmen(path, say=said.append)
    spec = _logmaps.grid_for(scans)
    fused, held = _logmaps.split(scans)
    beams = _logmaps.held_out_beams(held)
    drift = drifted(scans, log_seed(name))  # the whole log walks, the held-out scans too: as odometry would
    drifted_fused, _ = _logmaps.split(drift.scans)

    def score(risk: np.ndarray) -> _logmaps.Score:
        return _logmaps.score(_logmaps.predicted_ranges(risk, spec, beams), beams.ranges, spec.resolution)

    a, b = f"{name}-a", f"{name}-b"
    for map_name, posted in ((a, drifted_fused), (b, fused)):
        service.create(map_name, spec)
        service.post(map_name, posted)
    before = score(service.risk(a))
    path_msg = sensor_path(fused)
    rebuilds: list[tuple[float, dict[str, Any], float, float]] = []
    fusions: list[tuple[float, float]] = []
    for _ in range(REPEATS):  # in turn: a slow spell of the machine weighs on both sides, not on one
        cpu, started = service.cpu_s(), time.perf_counter()
        status = service.wait(a, service.correct(a, path_msg)["id"])
        if status["state"] != "done":
            raise RuntimeError(f"{a}: the rebuild failed: {status['error']}")
        rebuilds.append((float(status["elapsed_s"]), status, time.perf_counter() - started, service.cpu_s() - cpu))
        in_process = FuzzyMap(spec, SensorModel())
        t0, cpu = time.perf_counter(), time.process_time()
        _logmaps.fuse(in_process, fused, batch=BATCH)
        fusions.append((time.perf_counter() - t0, time.process_time() - cpu))
        del in_process
    _, status, put_to_done, rebuild_cpu_s = _median(rebuilds)
    in_process_s, in_process_cpu_s = _median(fusions)
    rebuilt, direct = service.risk(a), service.risk(b)
    stamps = [s.stamp_ns or 0 for s in scans]
    return LogReport(
        name=name, scans=len(scans), fused=len(fused), shape=spec.shape, drift=drift,
        duration_s=(stamps[-1] - stamps[0]) / 1e9, numbered=bool(said), drifted=before, rebuilt=score(rebuilt),
        direct=score(direct), identical=rebuilt.dtype == direct.dtype and np.array_equal(rebuilt, direct),
        status=status, put_to_done_s=put_to_done, rebuild_cpu_s=rebuild_cpu_s, in_process_s=in_process_s,
        in_process_cpu_s=in_process_cpu_s, path=path_msg,
        drifted_path=sensor_path(drifted_fused))


def _median(runs: list[_Run]) -> _Run:
    """The run whose first figure is the median (of an odd count; the lower middle of an even one)."""
    return sorted(runs, key=lambda run: run[0])[(len(runs) - 1) // 2]


# ---------------------------------------------------------------- the innocent beside rebuilds


@dataclass
class Beside:
    """The innocent's p99 (seconds) unloaded and during the rebuilds, by kind; the rebuilds it ran beside."""

    log: str
    unloaded: dict[str, tuple[float, int, int]]
    loaded: dict[str, tuple[float, int, int]]
    rebuilds: int
    seconds: float

    def ratio(self, kind: str) -> float:
        return self.loaded[kind][0] / self.unloaded[kind][0]

    @property
    def met(self) -> bool:
        return all(self.ratio(k) <= TARGET_P99 and not self.loaded[k][2] for k in self.loaded)


def beside_rebuilds(server: ServerProcess, service: Refusion, rep: LogReport, window_s: float) -> Beside:
    """The innocent's p99 while ``rep``'s map A is rebuilt again and again for at least ``window_s`` (drifted and
    corrected poses in turn, the corrected last, so A ends as it was), and unloaded: ``window_s`` before and half of
    it after, pooled (as ``bench abuse`` pools its quiet windows: other work on the machine moves either)."""
    fleet = Fleet.generate(1, 60, seed=11)
    service.client.call("POST", "/maps", json.dumps(fleet.map_request("innocent")).encode(), ok=(201,))
    setup = InnocentSetup(port=server.port, api_key="", name="innocent", scans=[s.binary() for s in fleet.scans[0]],
                          plan={}, kinds=("scan", "read"))
    innocent = Innocent(setup)
    try:
        time.sleep(3.0)  # its first requests (connections) are not the baseline
        quiet = (time.time(), time.time() + window_s)
        time.sleep(window_s)
        a = f"{rep.name}-a"
        start = time.time()
        rebuilds = 0
        while rebuilds % 2 == 1 or time.time() - start < window_s:
            path = rep.drifted_path if rebuilds % 2 == 0 else rep.path
            status = service.wait(a, service.correct(a, path)["id"], poll_s=POLL_LOADED_S)
            if status["state"] != "done":
                raise RuntimeError(f"{a}: a rebuild failed: {status['error']}")
            rebuilds += 1
        loaded = (start, time.time())
        time.sleep(1.0)  # the last switch's after-effects
        after = (time.time(), time.time() + window_s / 2)
        time.sleep(window_s / 2)
        samples, _ = innocent.stop()
    finally:
        innocent.kill()

    def p99(*windows: tuple[float, float]) -> dict[str, tuple[float, int, int]]:
        inside = [s for s in samples if any(a <= s[0] and s[1] < b for a, b in windows)]
        return {kind: innocent_latency(inside, windows[0][0], windows[-1][1], kind)[:3] for kind in setup.kinds}

    return Beside(rep.name, p99(quiet, after), p99(loaded), rebuilds, loaded[1] - loaded[0])


# ---------------------------------------------------------------- printing


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def quality_table(reports: Sequence[LogReport]) -> str:
    lines = [("| log | scans (fused) | drift: travelled, end / worst error, worst heading | within 2 cells: drifted A "
             "| rebuilt A | direct B | median error A / rebuilt / B | A and B risk.npy |"),
             "|---|---|---|---|---|---|---|---|"]
    for r in reports:
        d = r.drift
        lines.append(
            f"| {r.name} | {r.scans} ({r.fused}) | {d.travelled_m:.0f} m, {d.end_m:.2f} / {d.worst_m:.2f} m, "
            f"{math.degrees(d.worst_heading_rad):.1f} deg | {_pct(r.drifted.within)} | {_pct(r.rebuilt.within)} | "
            f"{_pct(r.direct.within)} | {r.drifted.row()[1]} / {r.rebuilt.row()[1]} / {r.direct.row()[1]} | "
            f"{'identical' if r.identical else '**differ**'} |")
    return "\n".join(lines)


def speed_table(reports: Sequence[LogReport]) -> str:
    lines = [(f"| log | scans re-fused | rebuild: elapsed_s / PUT to done (median of {REPEATS}) | scans/s | in-process integrate_batch "
             f"scans/s (median of {REPEATS}) | ratio (>= 0.9x) | by CPU: server / in-process s | log duration | x real time (>= 100x) |"),
             "|---|---|---|---|---|---|---|---|---|"]
    for r in reports:
        duration = (f"{r.duration_s:.1f} s: numbered at 5 Hz, its stamps do not increase (not judged)" if r.numbered
                    else f"{r.duration_s:.1f} s")
        lines.append(
            f"| {r.name} | {r.status['scans_total']} | {r.status['elapsed_s']:.2f} / {r.put_to_done_s:.2f} s | "
            f"{r.rebuild_rate:.0f} | {r.in_process_rate:.0f} ({r.in_process_s:.2f} s) | **{r.rate_ratio:.2f}x** | "
            f"{r.cpu_ratio:.2f}x: {r.rebuild_cpu_s:.2f} / {r.in_process_cpu_s:.2f} | {duration} | **{r.speed:.0f}x** |")
    return "\n".join(lines)


def beside_line(b: Beside) -> str:
    parts = [f"{kind} p99 {ms(b.loaded[kind][0])} against {ms(b.unloaded[kind][0])} unloaded "
             f"(**{b.ratio(kind):.1f}x**; n={b.loaded[kind][1]} / {b.unloaded[kind][1]}"
             f"{f', {b.loaded[kind][2]} failed' if b.loaded[kind][2] else ''})" for kind in b.loaded]
    return (f"innocent client beside {b.rebuilds} rebuilds of {b.log} ({b.seconds:.0f} s): " + "; ".join(parts)
            + f"; target <= {TARGET_P99:g}x {'met' if b.met else '**NOT met**'}")


def targets(reports: Sequence[LogReport], beside: Beside | None) -> list[tuple[str, bool]]:
    out = [("rebuilt A identical to B, same quality", all(r.identical and r.rebuilt == r.direct for r in reports)),
           (f"rebuild scans/s >= {TARGET_RATE:g}x in-process", all(r.rate_ratio >= TARGET_RATE for r in reports)),
           (f"rebuild >= {TARGET_SPEED:g}x the duration of the logs with real stamps",
            all(r.speed >= TARGET_SPEED for r in reports if not r.numbered))]
    if beside is not None:
        out.append((f"innocent p99 <= {TARGET_P99:g}x unloaded", beside.met))
    return out


# ---------------------------------------------------------------- the command


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench refusion", description=__doc__.split("\n\n")[0])
    _data.add_option(ap)
    ap.add_argument("--logs", help="comma-separated log names (e.g. orebro,fhw); default: every log there")
    ap.add_argument("--quick", action="store_true",
                    help=f"{' and '.join(QUICK_LOGS)} only, {QUICK_WINDOW_S:g} s windows (a CI-sized run)")
    ap.add_argument("--window", type=float, default=None,
                    help=f"seconds of the innocent's unloaded and loaded windows (default {WINDOW_S:g}; "
                         f"--quick {QUICK_WINDOW_S:g})")
    args = ap.parse_args(argv)
    _data.use(args)
    known = {_logmaps.log_name(p): p for p in _logmaps.log_paths()}
    wanted = [w.strip() for w in args.logs.split(",") if w.strip()] if args.logs else \
        list(QUICK_LOGS) if args.quick else sorted(known)
    unknown = [w for w in wanted if w not in known]
    if unknown:
        ap.error(f"unknown log(s) {unknown}; the logs are {sorted(known)}")
    window = args.window if args.window is not None else QUICK_WINDOW_S if args.quick else WINDOW_S

    began = time.perf_counter()
    print(f"# bench refusion, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(f"machine: {machine()}")
    print(f"logs: {', '.join(wanted)} ({_data.describe()}); 0.05 m cells, engine {DEFAULT_PRESET!r}; drift "
          f"{100 * DRIFT_POSITION_PER_M:g} % of each step's length in position, "
          f"{math.degrees(DRIFT_HEADING_RAD_PER_M):g} deg per metre in heading, seeded; held out: 1 scan in "
          f"{_logmaps.HOLDOUT_EVERY}", flush=True)
    _warm_up(DEFAULT_PRESET)
    reports: list[LogReport] = []
    beside: Beside | None = None
    with ServerProcess() as server:
        # kernels compiled before the first rebuild is timed (a fresh data directory holds no compiled code)
        wait_ready(httpx.Client(base_url=server.url, timeout=30.0), 300.0)
        service = Refusion(server)
        biggest: LogReport | None = None  # its maps stay for the innocent's run
        for name in wanted:
            rep = run_log(service, known[name])
            reports.append(rep)
            done_with = rep if biggest is not None and rep.fused <= biggest.fused else biggest
            biggest = rep if done_with is not rep else biggest
            if done_with is not None:
                for ab in "ab":
                    service.delete(f"{done_with.name}-{ab}")
            print(f"[{time.perf_counter() - began:4.0f} s] {name}: within 2 cells {_pct(rep.drifted.within)} drifted, "
                  f"{_pct(rep.rebuilt.within)} rebuilt, {_pct(rep.direct.within)} direct; "
                  f"{'identical' if rep.identical else 'DIFFER'}; rebuild {rep.rebuild_s:.2f} s "
                  f"(PUT to done {rep.put_to_done_s:.2f} s), "
                  f"{rep.rate_ratio:.2f}x in-process, {rep.speed:.0f}x real time", file=sys.stderr, flush=True)
        assert biggest is not None
        beside = beside_rebuilds(server, service, biggest, window)
        load = os.getloadavg()[0]

    print()
    print("## Held-out beam quality (bench maps' metric): drifted, rebuilt at the corrected poses, built from them")
    print()
    print(quality_table(reports))
    print()
    print("## The rebuild's speed (scans/s of the history re-fused; in-process: the same scans, same batches)")
    print()
    print(speed_table(reports))
    print()
    print(beside_line(beside))
    print()
    print("targets: " + "; ".join(f"{name} {'met' if ok else '**NOT met**'}" for name, ok in targets(reports, beside)))
    print(f"took {time.perf_counter() - began:.0f} s; load average at the end {load:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
