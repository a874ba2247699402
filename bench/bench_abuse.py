"""Hostile clients against the real server: each attack beside an innocent client, one row each.

    python3 dev.py bench abuse            (or .venv/bin/python -m bench.bench_abuse, from the repository root)

The server is ``python -m app`` on loopback (``bench._client.ServerProcess``) with ``FUZZYRISK_API_KEY``
set and every other setting at its README default (2 planner workers, warmed up). An innocent
client (``bench._abuse_clients.Innocent``, its own process) minds a small map of its own
throughout: a binary 1080-beam scan every 0.1 s, ``GET risk.npy`` every 0.1 s, an RRTConnect plan
(0.5 s) every second, each on its own connection, retried after ``Retry-After`` on a 503. Its
unloaded latency is measured in the same run: 20 s before the first attack and 15 s after the
last, pooled. Then, one after the other (7 and 8, storage damage and a batch
failing mid-apply, cannot be caused by a client: ``tests/app/test_storage.py``):

1.  a small batch of long rays on a 16 M-cell map (0.01 m): 12 LaserScans of 16,384 beams beyond
    ``range_max`` (a 1.0 MB body), back to back; then kill -9 and a restart (the batch must not be
    in the log);
2.  six 66 MB JSON bodies on ``POST /maps/x/risk/query`` at once with a wrong key (and one with
    none, one with the right key), again every second;
3.  40 uploads to one map, each sending 60 MB of a declared 60 MB + 1 in 1 MiB pieces every
    0.1 s, then nothing;
4.  200 connections trickling a request's headers, a byte a second;
4b. 8 uploads that send 16 MB, then a byte every 10 s (under ``FUZZYRISK_BODY_READ_TIMEOUT_S``), watched
    until ``FUZZYRISK_BODY_TIMEOUT_S`` has passed;
5.  16 M-cell maps created until ``FUZZYRISK_MAX_TOTAL_CELLS`` refuses, then small maps until
    ``FUZZYRISK_MAX_MAPS`` refuses, all deleted, round after round (the issue's 160 filled maps
    would take 24 GiB; the refusal comes at 23 empty ones);
6.  the heaviest scans the work budget takes on two maps at once: one LaserScan of 2 M beams
    (``FUZZYRISK_MAX_RAYS_PER_SCAN``) each, its range chosen so that its cast work is 95 % of
    ``FUZZYRISK_MAX_BATCH_CELLS`` (the issue's 166 s scans are refused now; these are the
    largest admitted), each map's client sending its next scan when the last is answered;
7.  an RRTstar plan of ``FUZZYRISK_MAX_PLAN_TIME_S`` on the 16 M-cell map;
8.  odd input: a scan POST without Content-Type, turning_radius 1e300, robot_radius 1e6,
    origin 1e300, a size that overflows, range_sigma 1e308 (and HEAD /health);
9.  10 clients flooding one map with 1 s RRTstar plans for 30 s;
10. the 16 M-cell map's ``occupancy_grid`` as JSON (refused now: 422 above 4 M cells, naming the .cdr
    and .mcap forms), then two clients reading it as CDR (16 MB) back to back for 30 s;
11. re-fusion: a 16 M-cell map of 3 long LaserScans (a rebuild of several seconds) given a corrected
    trajectory (``PUT /maps/a11/trajectory``), its rebuild waited for, then for 30 s a PUT a second after
    the last was answered, each superseding the rebuild the one before started; the last must be done.

Attacks that take a moment (rows 1, 2, 4, 5, 6, 8) are repeated for 30 s (``MIN_WINDOW_S``), so that
a row's p99 rests on about as many of the innocent's requests as the unloaded one. The attacking threads run at niceness 10 (``_attack_from_afar``): the server
and the innocent client, in processes of their own, at 0. Each row: what the attacker got (statuses, with the FUZZYRISK_* setting its message names), the
server's RSS growth (psutil: the server and its children, sampled every 0.1 s; peak in the window
minus the value at its start) against the budget the settings give that scenario, the innocent
client's p99 scan and read latency (and plan p99) during the attack and the ratio to its unloaded
p99, the load average, and a verdict: the attacker answered with a 4xx/503 naming the limit (or
served within its limits: rows 6, 7, 10, 11), RSS within budget, the innocent's p99 within 2x and none
of its requests failed, the server's pid unchanged. At the end the innocent map's version must
equal the scans it had acknowledged, before and after a kill -9 and restart.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import secrets
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil

from bench._abuse_clients import (
    Innocent,
    InnocentSetup,
    RawConn,
    body_steps,
    drive,
    request_head,
)
from bench._client import Fleet, ServerProcess, machine, percentile

API_KEY = secrets.token_urlsafe(24)
MB = 1e6
MiB = 2**20
CELL_BYTES = 13  # the README's bound on a fuzzy map of the default engine, bytes a cell
SNAPSHOT_CELL_BYTES = 12  # a fuzzy map's to_arrays (its snapshot before deflate): 11 bytes of state, 1 observed
SLACK = 64 * MiB  # working memory beside what a scenario's budget names (threads, caches, allocator)
LIMIT = re.compile(r"FUZZYRISK_[A-Z_]+")
HEAVY_ROOM = {"dimensions": 2, "resolution": 0.05, "origin": [-10.0, -10.0], "size": [20.0, 20.0]}
ATTACKER_NICE = 10  # see _attack_from_afar
#: A quick attack is repeated for this long, so that the innocent's p99 means something: about 300 reads and
#: scans, as many as in the unloaded windows (at 10 s, a row's p99 of 85 samples was its slowest request,
#: against the 4th slowest of the unloaded windows' 330)
MIN_WINDOW_S = 30.0
BIG_MAP = {"dimensions": 2, "resolution": 0.01, "origin": [-20.0, -20.0], "size": [40.0, 40.0], "model": "fuzzy"}


def _settings() -> Any:
    """The settings the server runs with: its environment is ours plus the key."""
    from app.config import Settings

    return Settings(api_key=API_KEY)


# ---------------------------------------------------------------- measurement


class RssSampler:
    """RSS of the server process and its children every 0.1 s, in a thread; follows a restarted server."""

    def __init__(self, server: ServerProcess) -> None:
        self.server = server
        self.samples: list[tuple[float, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def now(self) -> int:
        try:
            proc = psutil.Process(self.server.pid)
            total = proc.memory_info().rss
            for child in proc.children(recursive=True):
                try:
                    total += child.memory_info().rss
                except psutil.Error:
                    pass
            return total
        except (psutil.Error, AssertionError):
            return 0

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.server.alive():
                rss = self.now()
                if rss:
                    self.samples.append((time.time(), rss))
            self._stop.wait(0.1)

    def at(self, when: float) -> int:
        """The first sample taken at or after ``when`` (now, if none is yet)."""
        return next((v for t, v in self.samples if t >= when), 0) or self.now()

    def growth(self, start: float, end: float, at_start: int) -> tuple[int, int]:
        """(peak in [start, end] - ``at_start``, peak)."""
        peak = max([v for t, v in self.samples if start <= t <= end] + [at_start])
        return peak - at_start, peak

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


@dataclass
class Outcome:
    """What one scenario returns: what the attacker got, and the RSS budget the settings give it."""

    attacker: str
    attacker_ok: bool
    budget_bytes: float | None  # None: no setting bounds it (printed only)
    budget_note: str
    notes: list[str] = field(default_factory=list)
    plans_matter: bool = False  # the innocent's plans must all be served (rows 7 and 9)
    #: when the attack proper began (``time.time()``), after a set-up that is not the attack (row 11's map): the row's
    #: window, RSS growth and the innocent's latency, start there; None: with the scenario
    attack_from: float | None = None


@dataclass
class Row:
    key: str
    title: str
    outcome: Outcome
    start: float
    end: float
    rss_growth: int
    pid_ok: bool
    load: float
    lat: dict[str, tuple[float, int, int]] = field(default_factory=dict)  # kind -> (p99 s, samples, failures)
    verdict: str = ""
    ok: bool = False


def limits_named(messages: list[str]) -> str:
    names = sorted({m for msg in messages for m in LIMIT.findall(msg)})
    return ", ".join(names) if names else "no setting named"


def status_summary(answers: list[tuple[int | None, str]]) -> str:
    """'413 x1 (FUZZYRISK_...)' per status, in order of status."""
    by: Counter[tuple[Any, str]] = Counter((status, limits_named([message])) for status, message in answers)
    parts = []
    for (status, names), n in sorted(by.items(), key=lambda kv: (kv[0][0] is None, kv[0][0] or 0, kv[0][1])):
        label = "no answer" if status is None else str(status)
        parts.append(f"{label} x{n} ({names})")
    return "; ".join(parts)


def names_limit(status: int | None, message: str) -> bool:
    return status is not None and (400 <= status < 500 or status == 503) and bool(LIMIT.search(message))


def message_of(response: httpx.Response) -> str:
    try:
        body = response.json()
        details = body.get("details")
        return f"{body.get('message', '')}{f' {json.dumps(details)}' if details else ''}"
    except ValueError:
        return response.text[:300]


# ---------------------------------------------------------------- the run


@dataclass
class Ctx:
    server: ServerProcess
    client: httpx.Client
    settings: Any
    rss: RssSampler
    innocent: Innocent | None = None
    log: Callable[[str], None] = print
    heavy: tuple[float, int] = (0.0, 0)  # row 6: the range of its scans and their cast work (found before the run)

    def create(self, name: str, body: dict[str, Any]) -> httpx.Response:
        return self.client.post("/maps", json={"name": name, **body})

    def version(self, name: str) -> int:
        return int(self.client.get(f"/maps/{name}").json()["version"])

    def big_map(self) -> None:
        """Make the 16 M-cell map ``a1`` that rows 1, 7 and 10 use, unless an earlier row made it: a row run alone
        (``--only 10``) otherwise read a missing map, and its readers flooded the server with 404s."""
        if self.client.get("/maps/a1").status_code == 404:
            self.create("a1", BIG_MAP).raise_for_status()

    def wait_ready(self, timeout_s: float = 180.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{self.server.url}/ready", timeout=5).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"server not ready within {timeout_s} s:\n{self.server.log_tail()}")

    def restart(self) -> float:
        """kill -9 the server, start it on the same port and data; seconds until /ready."""
        assert self.innocent is not None
        if not self.innocent.pause():
            self.log("warning: the innocent client still had a request in flight at the kill")
        self.server.kill()
        started = time.perf_counter()
        self.server.start(port=self.server.port)
        self.wait_ready()
        took = time.perf_counter() - started
        self.client.close()
        self.client = httpx.Client(base_url=self.server.url, headers={"Authorization": f"Bearer {API_KEY}"},
                                   timeout=600.0)
        self.innocent.resume()
        return took


def s1_batch_work(ctx: Ctx) -> Outcome:
    ctx.big_map()
    beams, range_max = 16_384, 30.0
    scan = {"pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -math.pi, "angle_increment": 2 * math.pi / beams,
            "ranges": [range_max + 1.0] * beams, "range_min": 0.05, "range_max": range_max}
    body = json.dumps({"scans": [scan] * 12}, separators=(",", ":")).encode()
    answers: list[tuple[int, str]] = []
    took: list[float] = []
    until = time.monotonic() + MIN_WINDOW_S
    while time.monotonic() < until:
        t0 = time.perf_counter()
        response = ctx.client.post("/maps/a1/scans", content=body, headers={"Content-Type": "application/json"})
        took.append(time.perf_counter() - t0)
        answers.append((response.status_code, message_of(response)))
    kept = ctx.version("a1")
    ok = all(st == 413 and "FUZZYRISK_MAX_BATCH_CELLS" in m for st, m in answers) and kept == 0
    return Outcome(
        f"{status_summary(answers)} in {max(took):.2f} s at most: 12 x {beams:,} beams beyond range_max, "
        f"{len(body) / MB:.1f} MB body, sent back to back for {MIN_WINDOW_S:g} s; a1 at version {kept}",
        ok, 16e6 * CELL_BYTES + SLACK, "the 16 M-cell map (13 B/cell) + 64 MB",
        notes=[f"row 1: {answers[0][1].strip()[:200]}"])


def s2_keyless_bodies(ctx: Ctx) -> Outcome:
    size = 66 * 10**6
    item = b"[0.0, 0.0],"
    body = b'{"points": [' + item * ((size - 20) // len(item)) + b"[0.0, 0.0]]}"
    target = "/maps/x/risk/query"
    wrong = f"Bearer {API_KEY[:-1]}{'A' if API_KEY[-1] != 'A' else 'B'}"
    conns: list[RawConn] = []
    rounds = 0
    until = time.monotonic() + MIN_WINDOW_S
    while time.monotonic() < until:
        batch = []
        for _ in range(6):
            head = request_head("POST", target, {"Content-Type": "application/json",
                                                 "Content-Length": str(len(body)), "Authorization": wrong})
            batch.append(RawConn(ctx.server.port, body_steps(head, body, chunk=256 * 1024, interval_s=0.0), "wrong"))
        head = request_head("POST", target, {"Content-Type": "application/json", "Content-Length": str(len(body))})
        batch.append(RawConn(ctx.server.port, body_steps(head, body, chunk=256 * 1024, interval_s=0.0), "none"))
        head = request_head("POST", "/maps/a1/risk/query", {"Content-Type": "application/json",
                                                            "Content-Length": str(len(body)),
                                                            "Authorization": f"Bearer {API_KEY}"})
        batch.append(RawConn(ctx.server.port, body_steps(head, body, chunk=256 * 1024, interval_s=0.0), "right"))
        round_started = time.monotonic()
        drive(batch, 60.0)
        conns += batch
        rounds += 1
        # six at once, again every second: the bench shares the 2 cores, and a connection flood as fast as
        # this process can open them would measure the bench's CPU more than the server's defence
        time.sleep(max(0.0, 1.0 - (time.monotonic() - round_started)))
    keyless = [c for c in conns if c.label != "right"]
    right = [c for c in conns if c.label == "right"]
    sent = [c.sent_at_answer if c.sent_at_answer is not None else c.sent for c in keyless]
    ok = (all(c.status == 401 and "FUZZYRISK_API_KEY" in c.message for c in keyless)
          and all(c.status == 413 and "FUZZYRISK_MAX_JSON_BODY_BYTES" in c.message for c in right))
    return Outcome(
        f"{status_summary([(c.status, c.message) for c in keyless])} after {max(c.seconds for c in keyless):.2f} s "
        f"at most, {max(sent) / MB:.1f} of {len(body) / MB:.0f} MB sent (6 wrong keys and 1 none at once, "
        f"{rounds} rounds in {MIN_WINDOW_S:g} s); right key: {status_summary([(c.status, c.message) for c in right])}",
        ok, 32 * MiB, "32 MB (no body is read)")


def s3_slow_uploads(ctx: Ctx) -> Outcome:
    s = ctx.settings
    ctx.create("a3", {"dimensions": 2, "resolution": 0.05, "origin": [0.0, 0.0], "size": [10.0, 10.0]}).raise_for_status()
    declared = 60_000_001
    body = b'{"scans": [' + b" " * (declared - 1 - 11)  # 60,000,000 bytes of a valid beginning
    conns = []
    for _ in range(40):
        head = request_head("POST", "/maps/a3/scans", {"Content-Type": "application/json",
                                                       "Content-Length": str(declared),
                                                       "Authorization": f"Bearer {API_KEY}"})
        conns.append(RawConn(ctx.server.port, body_steps(head, body, chunk=MiB, interval_s=0.1)))
    drive(conns, s.body_read_timeout_s + 30.0)
    answers = [(c.status, c.message) for c in conns if c.status is not None]
    unanswered = [c for c in conns if c.status is None]
    ok = not unanswered and all(names_limit(st, m) for st, m in answers)
    kept = ctx.version("a3")
    return Outcome(
        f"{status_summary(answers)}{f'; unanswered {len(unanswered)}' if unanswered else ''}; "
        f"the last answer after {max(c.seconds for c in conns):.0f} s; a3 at version {kept}",
        ok and kept == 0, s.max_bodies_in_flight_bytes + SLACK,
        f"FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES ({s.max_bodies_in_flight_bytes / MiB:.0f} MiB) + 64 MB")


def s4_trickled_headers(ctx: Ctx) -> Outcome:
    s = ctx.settings

    def steps() -> Any:
        yield 0.0, b"GET /maps HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        for _ in range(int(s.header_timeout_s * 4)):
            yield 1.0, b"X"

    conns: list[RawConn] = []
    until = time.monotonic() + MIN_WINDOW_S
    while time.monotonic() < until:  # rounds of 200, each held until the server closes them
        round_ = [RawConn(ctx.server.port, steps()) for _ in range(200)]
        drive(round_, s.header_timeout_s * 3)
        conns += round_
    closed = [c.seconds for c in conns if c.how in ("closed", "reset")]
    answered = [(c.status, c.message) for c in conns if c.status is not None]
    still = sum(1 for c in conns if c.how == "deadline")
    in_time = all(s.header_timeout_s - 0.5 <= t <= s.header_timeout_s + 3.0 for t in closed)
    logged = "FUZZYRISK_HEADER_TIMEOUT_S" in ctx.server.log_tail(200_000)
    ok = len(closed) == len(conns) and in_time and logged
    return Outcome(
        f"closed x{len(closed)} after {min(closed, default=math.nan):.1f}-{max(closed, default=math.nan):.1f} s "
        f"(FUZZYRISK_HEADER_TIMEOUT_S = {s.header_timeout_s:g} s{', named in the server log' if logged else ''})"
        f"{f'; answered {status_summary(answered)}' if answered else ''}{f'; still open {still}' if still else ''}",
        ok, 32 * MiB, "32 MB (headers only)")


def s4b_trickled_bodies(ctx: Ctx) -> Outcome:
    s = ctx.settings
    declared, sent_first = 60_000_001, 16 * 10**6
    every = s.body_read_timeout_s / 3

    def steps() -> Any:
        head = request_head("POST", "/maps/a3/scans", {"Content-Type": "application/json",
                                                       "Content-Length": str(declared),
                                                       "Authorization": f"Bearer {API_KEY}"})
        yield from body_steps(head, b'{"scans": [' + b" " * (sent_first - 11), chunk=MiB, interval_s=0.0)
        for _ in range(100):
            yield every, b" "

    conns = [RawConn(ctx.server.port, steps()) for _ in range(8)]
    watch = max(s.body_read_timeout_s * 1.5, s.body_timeout_s + 5.0)  # the whole body's deadline, then some
    drive(conns, watch)
    open_ = [c for c in conns if c.how == "deadline"]
    answers = [(c.status, c.message) for c in conns if c.status is not None]
    ok = not open_ and all(names_limit(st, m) for st, m in answers)
    held = sum(c.sent for c in open_)
    parts = [status_summary(answers)] if answers else []
    if open_:
        parts.append(f"{len(open_)} of {len(conns)} still open after {watch:.0f} s, holding {held / MB:.0f} MB of "
                     f"FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES (FUZZYRISK_BODY_TIMEOUT_S = {s.body_timeout_s:g} s)")
    return Outcome("; ".join(parts), ok, s.max_bodies_in_flight_bytes + SLACK,
                   f"FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES + 64 MB; 16 MB + 1 byte / {every:g} s each")


def s5_maps(ctx: Ctx) -> Outcome:
    rounds: list[tuple[int, int, list[tuple[int, str]], int, int]] = []
    until = time.monotonic() + MIN_WINDOW_S
    while time.monotonic() < until:
        made: list[str] = []
        refused: list[tuple[int, str]] = []
        big = small = 0
        for i in range(1000):
            response = ctx.create(f"c5-{i:03d}", BIG_MAP)
            if response.status_code != 201:
                refused.append((response.status_code, message_of(response)))
                break
            made.append(f"c5-{i:03d}")
            big += 1
        for i in range(2000):
            response = ctx.create(f"m5-{i:04d}", {"dimensions": 2, "resolution": 0.1, "origin": [0.0, 0.0],
                                                  "size": [1.0, 1.0]})
            if response.status_code != 201:
                refused.append((response.status_code, message_of(response)))
                break
            made.append(f"m5-{i:04d}")
            small += 1
        deleted = sum(ctx.client.delete(f"/maps/{name}").status_code == 204 for name in made)
        rounds.append((big, small, refused, deleted, len(made)))
    ok = all(len(r) == 2 and all(st == 507 for st, _ in r) and "FUZZYRISK_MAX_TOTAL_CELLS" in r[0][1]
             and "FUZZYRISK_MAX_MAPS" in r[1][1] and d == m for _, _, r, d, m in rounds)
    big, small, refused, _, _ = rounds[0]
    biggest = max(b for b, *_ in rounds)
    return Outcome(
        f"{refused[0][0] if refused else '-'} ({limits_named(refused[0][1:])}) after {big} maps of 16 M cells; "
        f"{refused[1][0] if len(refused) > 1 else '-'} ({limits_named(refused[1][1:]) if len(refused) > 1 else ''}) "
        f"after {small} maps of 100 cells more; all deleted; {len(rounds)} rounds in {MIN_WINDOW_S:g} s",
        ok, biggest * 16e6 * CELL_BYTES + SLACK, f"13 B x the {biggest * 16} M cells it was let create + 64 MB")


def _heavy_scan_range(spec_map: dict[str, Any], beams: int, budget: int) -> tuple[float, int]:
    """The range that makes one ``beams``-beam LaserScan's cast work 95 % of ``budget`` (bisection)."""
    from fuzzyocc import GridSpec, LaserScan, cast_work

    spec = GridSpec(origin=tuple(spec_map["origin"]), size=tuple(spec_map["size"]), resolution=spec_map["resolution"])

    def work(r: float) -> int:
        scan = LaserScan(pose=(0.0, 0.0, 0.0), angle_min=-math.pi, angle_increment=2 * math.pi / beams,
                         ranges=np.full(beams, r), range_min=0.05, range_max=30.0)
        return cast_work(spec, [scan])

    lo, hi = 0.1, min(spec_map["size"]) / 2 - 0.1
    if work(hi) <= 0.95 * budget:
        return hi, work(hi)
    for _ in range(20):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if work(mid) <= 0.95 * budget else (lo, mid)
    return lo, work(lo)


def s6_heavy_scans(ctx: Ctx) -> Outcome:
    s = ctx.settings
    room = HEAVY_ROOM
    beams = s.max_rays_per_scan
    r, work = ctx.heavy
    body = np.full(beams, r, dtype="<f4").tobytes()
    query = {"x": 0.0, "y": 0.0, "theta": 0.0, "angle_min": -math.pi, "angle_increment": 2 * math.pi / beams,
             "range_min": 0.05, "range_max": 30.0}
    results: dict[str, list[tuple[int, float, str]]] = {"a6a": [], "a6b": []}
    until = time.monotonic() + MIN_WINDOW_S

    def post(name: str) -> None:  # one client a map, each sending its next scan when the last is answered
        while time.monotonic() < until:
            t0 = time.perf_counter()
            response = ctx.client.post(f"/maps/{name}/scans", params=query, content=body,
                                       headers={"Content-Type": "application/octet-stream"})
            results[name].append((response.status_code, time.perf_counter() - t0, message_of(response)))

    for name in ("a6a", "a6b"):
        ctx.create(name, room).raise_for_status()
    threads = [threading.Thread(target=post, args=(n,)) for n in results]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    answers = [a for got in results.values() for a in got]
    seconds = [a[1] for a in answers]
    cells = 2 * 400 * 400
    return Outcome(
        f"{status_summary([(a[0], a[2]) for a in answers])}, {min(seconds):.1f}-{max(seconds):.1f} s each: "
        f"scans of {beams / 1e6:.0f} M beams to {r:.2f} m each, {work / 1e6:.0f} M cells walked "
        f"({work / s.max_batch_cells:.0%} of FUZZYRISK_MAX_BATCH_CELLS), one after another on each of two maps "
        f"for {MIN_WINDOW_S:g} s",
        bool(answers) and all(a[0] == 200 for a in answers),
        s.max_bodies_in_flight_bytes + cells * CELL_BYTES + SLACK,
        "FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES + the two maps (13 B/cell) + 64 MB")


def s7_slow_plan(ctx: Ctx) -> Outcome:
    s = ctx.settings
    body = {"start": [-19.0, -19.0], "goal": [19.0, 19.0], "planner": "RRTstar", "time_limit": s.max_plan_time_s,
            "robot_radius": 0.2}
    ctx.big_map()
    t0 = time.perf_counter()
    response = ctx.client.post("/maps/a1/plan", json=body)
    took = time.perf_counter() - t0
    status = response.status_code
    detail = response.json().get("status", "") if status == 200 else limits_named([message_of(response)])
    bound = 3 * s.max_plan_time_s + 20  # the service's own bound on a worker (docs/DESIGN.md)
    return Outcome(
        f"{status} ({detail}) in {took:.0f} s: RRTstar, time_limit {s.max_plan_time_s:g} s "
        f"(FUZZYRISK_MAX_PLAN_TIME_S), 16 M-cell map",
        (status == 200 and took <= bound) or names_limit(status, message_of(response)),
        s.plan_cache_bytes * (1 + s.plan_workers) + SLACK,
        "FUZZYRISK_PLAN_CACHE_BYTES x (1 + FUZZYRISK_PLAN_WORKERS) + 64 MB", plans_matter=True)


def s8_odd_input(ctx: Ctx) -> Outcome:
    room = {"dimensions": 2, "resolution": 0.05, "origin": [0.0, 0.0], "size": [10.0, 10.0]}
    ctx.create("a8", room).raise_for_status()
    scan = {"pose": {"x": 5.0, "y": 5.0, "theta": 0.0}, "angle_min": -1.0, "angle_increment": 0.01,
            "ranges": ["inf"] * 200, "range_min": 0.05, "range_max": 4.0}
    plan = {"start": [1.0, 1.0, 0.0], "goal": [9.0, 9.0, 0.0], "planner": "RRTConnect", "time_limit": 0.5}
    cases: list[tuple[str, int, str, Callable[[], httpx.Response]]] = [
        ("scan POST without Content-Type", 415, "Content-Type",
         lambda: ctx.client.post("/maps/a8/scans", content=json.dumps({"scans": [scan]}).encode())),
        ("ReedsShepp turning_radius 1e300", 422, "turning_radius",
         lambda: ctx.client.post("/maps/a8/plan", json={**plan, "state_space": "ReedsShepp", "turning_radius": 1e300})),
        ("robot_radius 1e6", 422, "robot_radius",
         lambda: ctx.client.post("/maps/a8/plan", json={**plan, "start": [1.0, 1.0], "goal": [9.0, 9.0],
                                                        "robot_radius": 1e6})),
        ("origin 1e300", 422, "origin",
         lambda: ctx.create("a8-origin", {**room, "origin": [1e300, 1e300]})),
        ("size that overflows", 422, "size",
         lambda: ctx.create("a8-size", {**room, "size": [1e300, 1e300], "resolution": 1e-300})),
        ("range_sigma 1e308", 422, "range_sigma",
         lambda: ctx.create("a8-sigma", {**room, "sensor": {"range_sigma": 1e308}})),
    ]
    seen: dict[str, Counter[int]] = {label: Counter() for label, *_ in cases}
    ok = True
    notes = []
    rounds = 0
    until = time.monotonic() + MIN_WINDOW_S
    while time.monotonic() < until:
        rounds += 1
        for label, want, word, call in cases:
            response = call()
            msg = message_of(response)
            good = response.status_code == want and word.lower() in msg.lower()
            ok &= good
            seen[label][response.status_code] += 1
            if not good and len(notes) < 6:
                notes.append(f"row 8, {label}: {response.status_code} {msg[:200]}")
    got = [f"{label}: {'/'.join(str(st) for st in sorted(c))}" for label, c in seen.items()]
    head = ctx.client.head("/health")
    got.append(f"HEAD /health: {head.status_code}")
    listed = {m["name"] for m in ctx.client.get("/maps").json()}
    kept = ctx.version("a8")
    ok &= head.status_code == 200 and kept == 0 and not listed & {"a8-origin", "a8-size", "a8-sigma"}
    return Outcome("; ".join(got) + f" ({rounds} rounds in {MIN_WINDOW_S:g} s); a8 at version {kept}", ok, 32 * MiB, "32 MB (nothing accepted)", notes=notes)


def s9_plan_flood(ctx: Ctx) -> Outcome:
    s = ctx.settings
    ctx.create("a9", {"dimensions": 2, "resolution": 0.05, "origin": [0.0, 0.0], "size": [20.0, 20.0]}).raise_for_status()
    body = {"start": [1.0, 1.0], "goal": [19.0, 19.0], "planner": "RRTstar", "time_limit": 1.0}
    answers: list[tuple[int, str]] = []
    stop = time.monotonic() + MIN_WINDOW_S

    def flood() -> None:
        with httpx.Client(base_url=ctx.server.url, headers={"Authorization": f"Bearer {API_KEY}"}, timeout=120) as c:
            while time.monotonic() < stop:
                response = c.post("/maps/a9/plan", json=body)
                answers.append((response.status_code, message_of(response) if response.status_code != 200 else ""))
                if response.status_code == 503:
                    time.sleep(0.05)  # a flooder does not honour Retry-After, but gives the loop a breath

    threads = [threading.Thread(target=flood) for _ in range(10)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    refused = [(st, m) for st, m in answers if st != 200]
    ok = all(names_limit(st, m) for st, m in refused) and bool(refused)
    return Outcome(f"{status_summary(answers)} from 10 clients in {MIN_WINDOW_S:g} s", ok,
                   s.plan_cache_bytes * (1 + s.plan_workers) + SLACK,
                   "FUZZYRISK_PLAN_CACHE_BYTES x (1 + FUZZYRISK_PLAN_WORKERS) + 64 MB", plans_matter=True)


def s10_big_reads(ctx: Ctx) -> Outcome:
    # the big read: a JSON grid of more than 4 M cells is refused now (422 naming the .cdr and .mcap
    # forms; 16 M values as text held the GIL 1-3 s a read), so the readers take the form that is served
    ctx.big_map()
    refused = ctx.client.get("/maps/a1/occupancy_grid")
    answers: list[tuple[int, float, int]] = []
    stop = time.monotonic() + MIN_WINDOW_S

    def read() -> None:
        with httpx.Client(base_url=ctx.server.url, headers={"Authorization": f"Bearer {API_KEY}"}, timeout=300) as c:
            while time.monotonic() < stop:
                t0 = time.perf_counter()
                response = c.get("/maps/a1/occupancy_grid.cdr")
                answers.append((response.status_code, time.perf_counter() - t0, len(response.content)))

    threads = [threading.Thread(target=read) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    statuses = Counter(st for st, _, _ in answers)
    took = [d for _, d, _ in answers]
    size = max((n for _, _, n in answers), default=0)
    names_forms = ".cdr" in message_of(refused) and ".mcap" in message_of(refused)
    return Outcome(
        f"JSON: {refused.status_code}{' naming .cdr and .mcap' if names_forms else ''}; CDR: "
        f"{', '.join(f'{st} x{n}' for st, n in sorted(statuses.items()))}: {size / MB:.1f} MB each, "
        f"{min(took):.2f}-{max(took):.2f} s a read",
        refused.status_code == 422 and names_forms and bool(answers) and all(st == 200 for st in statuses), None,
        "none configured (printed only)")


REBUILD_SCANS = 3  # row 11: the LaserScans of its map, each walking 44 M cells of it (a rebuild of 7 s, load 4)
REBUILD_BEAMS = 16_384
REBUILD_PUT_EVERY_S = 1.0  # row 11: a PUT this long after the last was answered, superseding the rebuild it started


def _room_scans() -> list[Any]:
    """Row 11's scans: 360-degree LaserScans of a square room (its walls 1 m inside ``BIG_MAP``'s box), taken 1 s
    apart on a 5 m circle around its centre (in one batch, within ``FUZZYRISK_MAX_BATCH_CELLS``)."""
    from fuzzyocc import LaserScan

    half = -BIG_MAP["origin"][0] - 1.0
    step = 2 * math.pi / REBUILD_BEAMS
    scans = []
    for k in range(REBUILD_SCANS):
        phi = 2 * math.pi * k / REBUILD_SCANS
        x, y = 5.0 * math.cos(phi), 5.0 * math.sin(phi)
        angles = phi - math.pi + step * np.arange(REBUILD_BEAMS)
        d = np.stack([np.cos(angles), np.sin(angles)])
        with np.errstate(divide="ignore", invalid="ignore"):
            to_wall = np.where(d != 0.0, (np.sign(d) * half - np.array([[x], [y]])) / d, np.inf)
        scans.append(LaserScan(pose=(x, y, phi), angle_min=-math.pi, angle_increment=step, ranges=to_wall.min(axis=0),
                               range_min=0.05, range_max=40.0, stamp_ns=(1_800_000_000 + k) * 10**9))
    return scans


def s11_rebuilds(ctx: Ctx) -> Outcome:
    # bench_refusion imports this module: its path is imported when the row runs
    from app.cli.import_log import scan_json
    from bench.bench_refusion import sensor_path

    scans = _room_scans()
    ctx.create("a11", BIG_MAP).raise_for_status()
    ctx.client.post("/maps/a11/scans", json={"scans": [scan_json(s) for s in scans]}).raise_for_status()
    time.sleep(2.0)  # the map's fusion (its cast's memory) settles: the attack is what follows
    attack_from = time.time()
    moved = [dataclasses.replace(s, pose=(s.pose[0] + 0.05, s.pose[1], s.pose[2] + 0.01)) for s in scans]
    paths = [sensor_path(moved), sensor_path(scans)]
    answers: list[tuple[int, str]] = []
    took: list[float] = []

    def put(i: int) -> str | None:
        t0 = time.perf_counter()
        response = ctx.client.put("/maps/a11/trajectory", json=paths[i % 2])
        took.append(time.perf_counter() - t0)
        answers.append((response.status_code, message_of(response) if response.status_code != 202 else ""))
        return str(response.json()["rebuild"]["id"]) if response.status_code == 202 else None

    def done(rebuild_id: str | None) -> dict[str, Any]:
        deadline = time.monotonic() + 300.0
        while True:
            status = dict(ctx.client.get("/maps/a11/rebuild").json())
            if rebuild_id is None or (status["id"] == rebuild_id and status["state"] in ("done", "failed")):
                return status
            if time.monotonic() > deadline:
                raise RuntimeError(f"rebuild {rebuild_id} of a11 not done in 300 s: {status}")
            time.sleep(0.2)

    t0 = time.perf_counter()
    alone = done(put(0))
    alone_s = time.perf_counter() - t0
    puts, last = 1, None
    until = time.monotonic() + MIN_WINDOW_S
    while time.monotonic() < until:
        time.sleep(REBUILD_PUT_EVERY_S)
        last = put(puts)
        puts += 1
    t0 = time.perf_counter()
    final = done(last)
    final_s = time.perf_counter() - t0
    ok = (all(st == 202 for st, _ in answers) and alone["state"] == "done" and final["state"] == "done"
          and final["id"] == last)
    why = f" ({final['error']})" if final["state"] == "failed" else ""
    return Outcome(
        f"{status_summary(answers)} in {min(took):.1f}-{max(took):.1f} s: a rebuild alone {alone_s:.1f} s "
        f"({alone.get('scans_total')} scans of {REBUILD_BEAMS:,} beams, the 16 M-cell map), then for {MIN_WINDOW_S:g} s "
        f"a PUT {REBUILD_PUT_EVERY_S:g} s after the last was answered, each superseding the running rebuild; the last "
        f"{final['state']} {final_s:.1f} s after the window{why}; a11 at version {ctx.version('a11')} (the row from "
        f"the first PUT: the map was made and fused before it)",
        ok, 16e6 * (2 * CELL_BYTES + SNAPSHOT_CELL_BYTES) + SLACK,
        "the 16 M-cell map and one rebuild of it (13 B/cell each), the rebuild's snapshot arrays (12 B/cell) + 64 MB",
        attack_from=attack_from)


SCENARIOS: list[tuple[str, str, Callable[[Ctx], Outcome]]] = [
    ("1", "small batch of long rays, 16 M-cell map", s1_batch_work),
    ("2", "66 MB query bodies, wrong key, 6 at once", s2_keyless_bodies),
    ("3", "40 uploads of 60 MB of a declared 60 MB + 1", s3_slow_uploads),
    ("4", "200 connections trickling headers", s4_trickled_headers),
    ("4b", "8 uploads trickling their body", s4b_trickled_bodies),
    ("5", "maps past FUZZYRISK_MAX_TOTAL_CELLS, then FUZZYRISK_MAX_MAPS", s5_maps),
    ("6", "heaviest admitted scans on two maps", s6_heavy_scans),
    ("7", "a 30 s plan on the 16 M-cell map", s7_slow_plan),
    ("8", "odd input", s8_odd_input),
    ("9", "10 clients flooding one map with plans", s9_plan_flood),
    ("10", "occupancy_grid of the 16 M-cell map (JSON refused, CDR), 2 readers", s10_big_reads),
    ("11", "corrected trajectories PUT again and again on a 16 M-cell map, each superseding its rebuild", s11_rebuilds),
]


# ---------------------------------------------------------------- report


def innocent_latency(samples: list[tuple[float, float, str, int, int, str]], start: float, end: float,
                     kind: str) -> tuple[float, int, int, list[str]]:
    """(p99 seconds of the served requests, count, failures, failure notes) overlapping [start, end)."""
    mine = [s for s in samples if s[2] == kind and s[0] < end and s[1] >= start]
    served = [s[1] - s[0] for s in mine if s[3] == 200]
    failed = [f"{s[3]} {s[5]}" for s in mine if s[3] != 200]
    return percentile(served, 99), len(mine), len(failed), failed


def ms(seconds: float) -> str:
    if math.isnan(seconds):
        return "-"
    return f"{seconds * 1000:.0f} ms" if seconds < 10 else f"{seconds:.0f} s"


def mb(n: float) -> str:
    return f"{n / MB:+,.0f} MB" if abs(n) >= 0.5 * MB else f"{n / MB:+.1f} MB"


def _exception(line: str) -> str:
    """The last line of a kv log record's traceback (its exception), or its message."""
    match = re.search(r'exc="(.*)"', line)
    if match:
        last = [part for part in match.group(1).split("\\n") if part.strip()]
        return last[-1].strip()[:160] if last else "?"
    match = re.search(r'msg="([^"]*)"', line)
    return match.group(1)[:160] if match else line[:160]


def _attack_from_afar() -> None:
    """Run this thread (the attacks') at niceness 10, and so the threads it starts.

    An attacker's CPU is its own machine's; here the attacking clients share the server's 2 cores,
    and at equal priority their own HTTP work (up to a core: 800 requests a second in row 10) was
    taken from the server and the innocent client, which a remote attacker's is not. Niced, they
    take the CPU the server leaves: the pressure on the server is what the server lets through.
    """
    from app.ops.process_setup import lower_priority

    lower_priority(ATTACKER_NICE)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="comma-separated scenario keys (default: all)")
    parser.add_argument("--server-log", default="/tmp/bench-abuse-server.log", help="where the server's log is kept")
    parser.add_argument("--samples", default="/tmp/bench-abuse-samples.json",
                        help="where the innocent's requests (start, end, kind, status) and the rows' windows are kept")
    args = parser.parse_args(argv)
    only = {k for k in args.only.split(",") if k}
    settings = _settings()
    began = time.time()
    print(f"# bench abuse, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(f"machine: {machine()}")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False).stdout.strip()
    print(f"code: {commit or '?'}; server: python -m app, loopback, FUZZYRISK_API_KEY set, every other setting "
          f"at its default (FUZZYRISK_MAX_BATCH_CELLS {settings.max_batch_cells:,}, "
          f"FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES {settings.max_bodies_in_flight_bytes:,}, "
          f"FUZZYRISK_BODY_READ_TIMEOUT_S {settings.body_read_timeout_s:g}, "
          f"FUZZYRISK_HEADER_TIMEOUT_S {settings.header_timeout_s:g}, FUZZYRISK_PLAN_WORKERS {settings.plan_workers}, "
          f"FUZZYRISK_FUSION_THREADS {settings.fusion_threads}, FUZZYRISK_READ_THREADS {settings.read_threads})",
          flush=True)

    fleet = Fleet.generate(1, 60, seed=11)
    heavy = _heavy_scan_range(HEAVY_ROOM, settings.max_rays_per_scan, settings.max_batch_cells)
    server = ServerProcess(env={"FUZZYRISK_API_KEY": API_KEY, "FUZZYRISK_PLAN_WORKERS": str(settings.plan_workers),
                                "FUZZYRISK_PLAN_WARMUP": "true"})
    rss: RssSampler | None = None
    # the attacks run here, at a lower priority; the server (restarts included) and the innocent start from
    # the main thread, at the priority the bench was given
    attackers = ThreadPoolExecutor(1, thread_name_prefix="attacker", initializer=_attack_from_afar)
    innocent: Innocent | None = None
    ctx: Ctx | None = None
    rows: list[Row] = []
    try:
        server.start()
        ctx = Ctx(server, httpx.Client(base_url=server.url, headers={"Authorization": f"Bearer {API_KEY}"},
                                       timeout=600.0), settings, RssSampler(server), heavy=heavy)
        rss = ctx.rss
        ctx.wait_ready()
        ctx.client.post("/maps", json=fleet.map_request("innocent")).raise_for_status()
        points = fleet.free_points
        far = int(np.argmax(np.linalg.norm(points - points[0], axis=1)))
        plan = {"start": points[0].tolist(), "goal": points[far].tolist(), "planner": "RRTConnect",
                "time_limit": 0.5, "robot_radius": 0.2}
        setup = InnocentSetup(port=server.port, api_key=API_KEY, name="innocent",
                              scans=[s.binary() for s in fleet.scans[0]], plan=plan)
        innocent = ctx.innocent = Innocent(setup)
        time.sleep(5.0)  # its first requests (connections, the first plan's grid) are not the baseline
        base1 = (time.time(), time.time() + 20.0)
        time.sleep(20.0)
        print(f"unloaded baseline 1: {base1[1] - base1[0]:.0f} s, load average {os.getloadavg()[0]:.1f}", flush=True)

        for key, title, run in SCENARIOS:
            if only and key not in only:
                continue
            time.sleep(2.0)  # let the previous scenario's after-effects settle
            pid = server.pid
            at_start = rss.now()
            start = time.time()
            try:
                outcome = attackers.submit(run, ctx).result()
            except Exception as exc:  # noqa: BLE001 - a scenario that breaks is a row that says so
                outcome = Outcome(f"bench error: {type(exc).__name__}: {str(exc)[:200]}", False, None, "")
            end = time.time()
            if outcome.attack_from is not None:
                start, at_start = outcome.attack_from, rss.at(outcome.attack_from)
            time.sleep(0.3)
            growth, _ = rss.growth(start, end + 0.3, at_start)
            row = Row(key, title, outcome, start, end, growth, server.alive() and server.pid == pid,
                      os.getloadavg()[0])
            rows.append(row)
            print(f"[{time.time() - began:5.0f} s] {key} {title}: {outcome.attacker}; RSS {mb(growth)}; "
                  f"{end - start:.0f} s", flush=True)
            if key == "1" and server.alive():
                took = ctx.restart()
                kept = ctx.version("a1")
                outcome.attacker += f"; kill -9 + restart: ready in {took:.0f} s, a1 at version {kept}"
                outcome.attacker_ok &= kept == 0
                print(f"    restart after row 1: ready in {took:.1f} s, a1 at version {kept}", flush=True)

        time.sleep(2.0)
        base2 = (time.time(), time.time() + 15.0)
        time.sleep(15.0)
        print(f"unloaded baseline 2: 15 s, load average {os.getloadavg()[0]:.1f}", flush=True)
        samples, acked = innocent.stop()
        innocent = ctx.innocent = None
        version_before = ctx.version("innocent")
        errors_in_log = [ln for ln in server.log_tail(50_000_000).splitlines()
                         if "level=ERROR" in ln or "Traceback" in ln]
        server.kill()
        t0 = time.perf_counter()
        server.start(port=server.port)
        ctx.wait_ready()
        restart_s = time.perf_counter() - t0
        with httpx.Client(base_url=server.url, headers={"Authorization": f"Bearer {API_KEY}"}, timeout=60) as c:
            version_after = int(c.get("/maps/innocent").json()["version"])
            maps_after = sorted(m["name"] for m in c.get("/maps").json())
    finally:
        attackers.shutdown(wait=False, cancel_futures=True)
        if innocent is not None:
            innocent.kill()
        if rss is not None:
            rss.stop()
        if ctx is not None:
            ctx.client.close()
        if server.log_path is not None and server.log_path.exists():
            import shutil

            shutil.copy(server.log_path, args.server_log)
        server.close()

    Path(args.samples).write_text(json.dumps({
        "samples": [list(s[:4]) for s in samples], "baselines": [base1, base2],
        "rows": [{"key": r.key, "start": r.start, "end": r.end} for r in rows]}))

    # ---- the unloaded reference: both quiet windows, pooled
    ref: dict[str, float] = {}
    for kind in ("scan", "read", "plan"):
        pooled = [s[1] - s[0] for s in samples if s[2] == kind and s[3] == 200
                  and any(a <= s[0] and s[1] < b for a, b in (base1, base2))]
        ref[kind] = percentile(pooled, 99)
        p1 = innocent_latency(samples, *base1, kind)[0]
        p2 = innocent_latency(samples, *base2, kind)[0]
        print(f"innocent unloaded p99 {kind}: {ms(ref[kind])} (baseline 1: {ms(p1)}, baseline 2: {ms(p2)}; "
              f"{len(pooled)} samples)")

    failures_all: list[str] = []
    for row in rows:
        reasons = []
        if not row.outcome.attacker_ok:
            reasons.append("attacker answer")
        if row.outcome.budget_bytes is not None and row.rss_growth > row.outcome.budget_bytes:
            reasons.append("RSS")
        for kind in ("scan", "read", "plan"):
            p99, n, failed, notes = innocent_latency(samples, row.start, row.end, kind)
            row.lat[kind] = (p99, n, failed)
            judged = kind != "plan" or row.outcome.plans_matter
            if failed and (judged or kind == "plan"):
                reasons.append(f"{failed} innocent {kind}{'s' if failed > 1 else ''} failed")
                failures_all += [f"row {row.key}, innocent {kind}: {note}" for note in notes[:3]]
            if judged and kind != "plan" and (math.isnan(p99) or p99 > 2 * ref[kind]):
                reasons.append(f"{kind} p99 {p99 / ref[kind]:.1f}x" if not math.isnan(p99) else f"no {kind} served")
        if not row.pid_ok:
            reasons.append("server pid changed")
        row.ok = not reasons
        row.verdict = "yes" if row.ok else "no: " + ", ".join(reasons)

    print()
    print("| # | attack | the attacker got | server RSS growth (budget) | innocent scan p99 (x unloaded) "
          "| innocent read p99 (x unloaded) | innocent plan p99 | load | within budgets |")
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        budget = (f"{row.outcome.budget_bytes / MB:,.0f} MB: {row.outcome.budget_note}"
                  if row.outcome.budget_bytes is not None else row.outcome.budget_note)

        def cell(kind: str, row: Row = row) -> str:
            p99, n, failed = row.lat[kind]
            ratio = f" ({p99 / ref[kind]:.1f}x)" if not math.isnan(p99) else ""
            return f"{ms(p99)}{ratio}, n={n}{f', {failed} failed' if failed else ''}"

        print(f"| {row.key} | {row.title} | {row.outcome.attacker} | {mb(row.rss_growth)} ({budget}) | "
              f"{cell('scan')} | {cell('read')} | {cell('plan')} | {row.load:.1f} | {row.verdict} |")
    print()
    print(f"unloaded p99 (both quiet windows pooled): scan {ms(ref['scan'])}, read {ms(ref['read'])}, "
          f"plan {ms(ref['plan'])}")
    lost = len(acked) - version_before
    kept_ok = version_before == len(acked) and version_after == len(acked)
    print(f"innocent map: {len(acked)} scans acknowledged, version {version_before} at the end, {version_after} after "
          f"kill -9 + restart (ready in {restart_s:.0f} s; {len(maps_after)} maps loaded: {', '.join(maps_after)}); "
          f"acknowledged batches lost: {max(lost, 0)}")
    kinds = Counter(_exception(line) for line in errors_in_log)
    print(f"server log ({args.server_log}): {len(errors_in_log)} ERROR records"
          + "".join(f"; {n} x {kind}" for kind, n in kinds.most_common()))
    for note in failures_all[:10]:
        print(f"    {note[:300]}")
    for row in rows:
        for note in row.outcome.notes:
            print(f"    {note[:300]}")
    every = all(r.ok for r in rows) and kept_ok
    print(f"took {time.time() - began:.0f} s; load average {' / '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print(f"every scenario within its budgets: {'yes' if every else 'no'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
