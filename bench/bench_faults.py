"""Crash and storage faults: kill -9 at random moments, a full disk, a read-only data directory.

    python -m bench.bench_faults [--kills 20] [--seed 1] [--skip-storage]   (from the repository root)
    python -m bench.bench_faults --replicas 2 [--kills 12] [--seed 1] [--database-url URL]   (section 4 only)

1. **kill -9.** One client streams scan batches (JSON batches of 3 scans and binary single
   scans, alternating) into a fuzzy and a Bayes map while a timer SIGKILLs the server at a
   random moment (uniform in 0.05 .. 1.5 s after the stream resumes; snapshots every 5 batches,
   so kills also land in snapshot writes). After each kill the server is restarted on the same
   data directory and every map is checked against an in-process replay (``fuzzyocc``) of
   exactly the acknowledged batches (a batch is acknowledged when its 200 arrived), plus the
   batch in flight if the map's version says it was committed:

   * acknowledged batches lost: ``last acknowledged version - version after restart`` (must be 0)
   * maps that fail to load: missing from ``GET /maps`` or the server does not start (0)
   * half-applied batches: ``scans_fused`` that no whole number of batches explains (0)
   * risk mismatches: the ``.npy`` risk differs from the replay in any bit (0)
   * version jumps: a version neither the acknowledged one nor the one after it (0)

2. **Full disk.** The data directory is a 3 MB tmpfs (``mount -t tmpfs -o size=3m``; when
   mounting is not permitted, the server runs under ``RLIMIT_FSIZE`` instead and the method is
   printed). Batches are posted until one is refused; the refusal must be a 5xx with a JSON
   error body (503 expected), the map must keep its version and risk, the service must answer
   again once space is back (tmpfs grown), and a kill -9 + restart must load the same map.

3. **Read-only data directory.** The server is stopped, the tmpfs remounted read-only
   (``mount -o remount,ro``; the kernel refuses that under a running server's open files, and
   as non-root ``chmod a-w`` does the same) and the server started on it: it must start, serve
   reads, and answer writes with a 5xx carrying a JSON error body; finally the directory is made
   writable again and the map checked against the acknowledged batches.

4. **Replicas on one PostgreSQL (``--replicas N``).** A PostgreSQL cluster is started
   here with fsync on (``bench._fleet.durable_postgres``), N ``python -m app`` replicas on one
   database (own data directories and ports; snapshots every 5 batches), 3 maps. Three writer
   threads post batches, each to a random map through a random replica that is up, and a reader
   reads a random map's risk through a random replica every 0.25 s. One replica at a time (in
   turn) is SIGKILLed at a random moment (1-3 s after the last restart); the survivor is read at
   once (each map's risk ``.npy`` in turn, timed from the kill, target 1 s) while the writers go on
   through it; 0.3-1 s later the killed replica restarts on its data directory and reads every map
   (loads it: a snapshot, maybe the other replica's, and the log after it). The database carries
   audit triggers of the bench (``bench_batches``, ``bench_snapshots``: every batch row ever
   committed, with the replica that committed it, and every snapshot written), so that batches
   folded into a snapshot can still be compared with what was sent. At the end (writers stopped):

   * acknowledged batches lost: an acknowledged version missing from the log (or above the map's
     version, or discarded); stored with other content: the batch committed as that version is not
     the one acknowledged (``app.maps.logcodec.encode`` of the scans sent, byte for byte, once the stamps the
     service gave them are taken off) (both 0)
   * versions acknowledged twice, version gaps, committed versions that were never acknowledged and
     are not a batch whose request a kill cut (0)
   * divergent replicas: one (map, version) whose ``.npy`` bytes or ETag differ between replicas
     (every read of the run counts; at the end each map is read through every replica), or a replica
     behind the database's version after a read (0)
   * half-applied: a read (any replica, any moment: survivors', restarted replica's, the reader's,
     the final ones) whose risk differs from an in-process replay of every committed batch up to
     its version, or ``scans_fused`` differing from it; and ``app.maps.stored.restore(load_map)``
     (snapshot + log) differing from the replay of every batch (0)
   * survivor reads slower than 1 s after a kill; unexpected answers (any non-200, or a connection
     error from a replica that was not being killed); ``level=ERROR`` records in the logs (0)
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import math
import os
import random
import resource
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench._client import Batch, Fleet, ServerProcess, machine, new_map, npy_array
from bench._fleet import Replicas, durable_postgres

MAPS = {"fz": "fuzzy", "bz": "bayes"}
FAULT_ENV = {"FUZZYRISK_SNAPSHOT_EVERY": "5", "FUZZYRISK_DISK_RESERVE_BYTES": str(256 * 2**10)}  # a 3 MB volume


# ---------------------------------------------------------------- the mirror of one map


@dataclass
class Mirror:
    """What a map must hold: an in-process replay of the acknowledged batches."""

    name: str
    model: str
    fleet: Fleet
    map: Any = None
    version: int = 0  # version the replay is at
    acked: list[tuple[int, Batch]] = field(default_factory=list)  # acknowledged, not yet replayed
    in_flight: Batch | None = None
    diverged: bool = False  # a loss was found: later comparisons would only repeat it

    def __post_init__(self) -> None:
        self.map = new_map(self.fleet.spec, self.model)

    @property
    def last_acked(self) -> int:
        return self.acked[-1][0] if self.acked else self.version


@dataclass
class KillCounts:
    kills: int = 0
    batches_acked: int = 0
    batches_in_flight: int = 0
    in_flight_committed: int = 0
    acked_lost: int = 0
    maps_failed_to_load: int = 0
    server_failed_to_start: int = 0
    half_applied: int = 0
    risk_mismatches: int = 0
    version_jumps: int = 0
    other_errors: list[str] = field(default_factory=list)
    kill_to_ready_s: list[float] = field(default_factory=list)
    server_log_errors: list[str] = field(default_factory=list)  # diagnostics: ERROR records of the server

    def failures(self) -> int:
        return (self.acked_lost + self.maps_failed_to_load + self.server_failed_to_start + self.half_applied
                + self.risk_mismatches + self.version_jumps + len(self.other_errors))


def _batches(fleet: Fleet) -> list[Batch]:
    """JSON batches of 3 scans and binary single scans, alternating, from both robots."""
    json_batches = fleet.batches(0, 3, binary=False)
    binary = fleet.batches(1, 1, binary=True)
    out: list[Batch] = []
    for i in range(max(len(json_batches), len(binary))):
        if i < len(json_batches):
            out.append(json_batches[i])
        if i < len(binary):
            out.append(binary[i])
    return out


def verify(client: httpx.Client, mirrors: dict[str, Mirror], counts: KillCounts) -> None:
    """Compare every map of the restarted server with its mirror; advance the mirrors."""
    listed = {m["name"]: m for m in client.get("/maps").json()}
    for name, mirror in mirrors.items():
        info = listed.get(name)
        if info is None:
            counts.maps_failed_to_load += 1
            mirror.diverged = True
            continue
        version, last = int(info["version"]), mirror.last_acked
        include_in_flight = False
        if version < last:
            counts.acked_lost += last - version
            mirror.diverged = True
        elif version == last + 1 and mirror.in_flight is not None:
            include_in_flight = True  # committed before the kill: it is the map's now
            counts.in_flight_committed += 1
        elif version != last:
            counts.version_jumps += 1
            mirror.diverged = True
        if mirror.diverged:
            mirror.acked.clear()
            mirror.in_flight = None
            continue
        todo = [b for _, b in mirror.acked] + ([mirror.in_flight] if include_in_flight and mirror.in_flight else [])
        for batch in todo:
            mirror.map.integrate_batch(batch.laser_scans())
        mirror.version = version
        mirror.acked.clear()
        mirror.in_flight = None
        if int(info["scans_fused"]) != mirror.map.scans_fused:
            counts.half_applied += 1
            mirror.diverged = True
            continue
        response = client.get(f"/maps/{name}/risk", params={"format": "npy"})
        if response.status_code != 200:
            counts.maps_failed_to_load += 1
            continue
        if not np.array_equal(npy_array(response), mirror.map.risk()):
            counts.risk_mismatches += 1
            mirror.diverged = True


def kill_loop(kills: int, seed: int = 1, *, log: Callable[[str], None] = print,
              max_delay_s: float = 1.5, database_url: str | None = None) -> KillCounts:
    """Stream batches and kill -9 the server ``kills`` times; the counts of section 1.

    ``database_url``: the server keeps its maps in that PostgreSQL database instead of its SQLite file.
    """
    rng = random.Random(seed)
    fleet = Fleet.generate(2, 40, seed=seed)
    batches = _batches(fleet)
    mirrors = {name: Mirror(name, model, fleet) for name, model in MAPS.items()}
    counts = KillCounts()
    server = ServerProcess(env={**FAULT_ENV, **({"FUZZYRISK_DATABASE_URL": database_url} if database_url else {})})
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=30.0) as client:
            for name, model in MAPS.items():
                client.post("/maps", json=fleet.map_request(name, model)).raise_for_status()
        k = 0  # next batch
        for n in range(kills):
            delay = rng.uniform(0.05, max_delay_s)
            timer = threading.Timer(delay, server.kill)
            with httpx.Client(base_url=server.url, timeout=30.0) as client:
                timer.start()
                while True:
                    name = list(MAPS)[k % len(MAPS)]
                    batch = batches[(k // len(MAPS)) % len(batches)]
                    mirror = mirrors[name]
                    try:
                        response = batch.post(client, name)
                    except httpx.HTTPError:
                        mirror.in_flight = batch
                        counts.batches_in_flight += 1
                        break
                    k += 1
                    if response.status_code != 200:
                        counts.other_errors.append(
                            f"{name} batch (after version {mirror.last_acked}) answered {response.status_code}: "
                            f"{response.text[:200]}")
                        continue
                    version = int(response.json()["version"])
                    if version != mirror.last_acked + 1:
                        counts.version_jumps += 1
                    mirror.acked.append((version, batch))
                    counts.batches_acked += 1
            timer.join()
            server.kill()  # a no-op when the timer got it; the processes are gone either way
            counts.kills += 1
            t0 = time.perf_counter()
            try:
                server.start()
            except RuntimeError as exc:
                counts.server_failed_to_start += 1
                log(f"kill {n + 1}: server did not start again: {exc}")
                break
            counts.kill_to_ready_s.append(time.perf_counter() - t0)
            with httpx.Client(base_url=server.url, timeout=60.0) as client:
                verify(client, mirrors, counts)
            log(f"kill {n + 1:2d} after {delay:4.2f} s: versions "
                f"{', '.join(f'{m.name}={m.version}' for m in mirrors.values())}; "
                f"in flight committed {counts.in_flight_committed}/{counts.batches_in_flight}; failures so far "
                f"{counts.failures()}")
    finally:
        counts.server_log_errors = [line[-600:] for line in server.log_tail(10**7).splitlines() if "level=ERROR" in line]
        server.close()
    return counts


# ---------------------------------------------------------------- storage faults


@dataclass
class Volume:
    """A small data directory that can fill up and turn read-only."""

    path: Path
    method: str  # "tmpfs" or "rlimit/chmod"
    size_bytes: int

    @classmethod
    def make(cls, size_bytes: int) -> Volume:
        path = Path(tempfile.mkdtemp(prefix="fuzzyrisk-faults-")) / "vol"
        path.mkdir()
        try:
            subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_bytes}", "tmpfs", str(path)],
                           check=True, capture_output=True)
            return cls(path, "tmpfs", size_bytes)
        except (OSError, subprocess.CalledProcessError):
            return cls(path, "rlimit/chmod", size_bytes)

    def grow(self, size_bytes: int) -> None:
        """Give the directory more room (space freed)."""
        if self.method == "tmpfs":
            subprocess.run(["mount", "-o", f"remount,size={size_bytes}", str(self.path)], check=True)
        self.size_bytes = size_bytes

    def read_only(self, ro: bool) -> None:
        if self.method == "tmpfs":
            subprocess.run(["mount", "-o", "remount," + ("ro" if ro else "rw"), str(self.path)], check=True)
        else:
            mode = 0o555 if ro else 0o755
            for p in [self.path, *self.path.rglob("*")]:
                os.chmod(p, mode if p.is_dir() else (0o444 if ro else 0o644))

    def server_env(self) -> dict[str, str]:
        return dict(FAULT_ENV)

    def preexec(self) -> Callable[[], None] | None:
        """Without tmpfs, a file-size limit stands in for the full disk (Python ignores SIGXFSZ)."""
        if self.method == "tmpfs":
            return None
        limit = self.size_bytes

        def set_limit() -> None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

        return set_limit

    def cleanup(self) -> None:
        if self.method == "tmpfs":
            subprocess.run(["umount", "-l", str(self.path)], capture_output=True)
        import shutil

        shutil.rmtree(self.path.parent, ignore_errors=True)


@dataclass
class StorageReport:
    method: str
    disk_full_after: int = 0  # batches acknowledged before the first refusal
    disk_full_status: int = 0
    disk_full_body: str = ""
    disk_full_json_detail: bool = False
    statuses_while_full: dict[int, int] = field(default_factory=dict)
    delete_while_full: str = ""  # DELETE of another map while the disk is full: its status (204: space freed)
    refused_but_applied: int = 0  # batches answered with an error that the map applied anyway
    map_intact_while_full: bool = False
    map_note_while_full: str = ""
    recovered_after_space: bool = False
    recovered_status: str = ""
    restart_after_full_ok: bool = False
    restart_after_full_note: str = ""
    ro_status: int = 0
    ro_body: str = ""
    ro_json_detail: bool = False
    ro_reads_ok: bool = False
    ro_restart: str = ""
    ro_final_ok: bool = False
    ro_final_note: str = ""
    other: list[str] = field(default_factory=list)

    def failures(self) -> list[str]:
        out = []
        if not (500 <= self.disk_full_status < 600 and self.disk_full_json_detail):
            out.append(f"full disk answered {self.disk_full_status} {self.disk_full_body[:80]!r}, "
                       "not a 5xx with a JSON detail")
        if not self.delete_while_full.startswith("204"):
            out.append(f"a map could not be deleted while the disk was full: {self.delete_while_full[:160]}")
        if self.refused_but_applied:
            out.append(f"{self.refused_but_applied} batch(es) answered with an error were applied anyway "
                       "(a client that retries applies them twice)")
        if not self.map_intact_while_full:
            out.append(f"while the disk was full: {self.map_note_while_full}")
        if not self.recovered_after_space:
            out.append(f"no recovery once space was back: {self.recovered_status[:160]}")
        if not self.restart_after_full_ok:
            out.append(f"restart after the full disk: {self.restart_after_full_note}")
        if self.ro_restart.startswith("refused"):
            out.append(f"on a read-only data directory the service {self.ro_restart[:200]}")
        else:
            if not (500 <= self.ro_status < 600 and self.ro_json_detail):
                out.append(f"read-only dir: a batch answered {self.ro_status} {self.ro_body[:80]!r}, "
                           "not a 5xx with a JSON detail")
            if not self.ro_reads_ok:
                out.append("reads failed on the read-only directory")
        if not self.ro_final_ok:
            out.append(f"after the read-only episode: {self.ro_final_note}")
        return out + self.other


def _json_detail(response: httpx.Response) -> bool:
    try:
        body = response.json()
    except ValueError:
        return False
    # the service's one error body: {code, message, details}
    return isinstance(body, dict) and isinstance(body.get("code"), str) and bool(body.get("message"))


def _check_map(client: httpx.Client, mirror: Mirror, refused: list[Batch] | None = None) -> tuple[bool, str, int]:
    """(map as acknowledged, note, refused batches that were applied anyway).

    A batch answered with an error must not be applied; if the version says some were,
    they are replayed (in the order they were refused) so that the risk is still checked.
    """
    info = client.get(f"/maps/{mirror.name}")
    if info.status_code != 200:
        return False, f"GET /maps/{mirror.name} answered {info.status_code}", 0
    version = info.json()["version"]
    for _, batch in mirror.acked:
        mirror.map.integrate_batch(batch.laser_scans())
    if mirror.acked:
        mirror.version = mirror.acked[-1][0]
    mirror.acked.clear()
    risk = client.get(f"/maps/{mirror.name}/risk", params={"format": "npy"})
    if risk.status_code != 200:
        return False, f"GET /maps/{mirror.name}/risk answered {risk.status_code}", 0
    served = npy_array(risk)
    applied_anyway = 0
    if refused and mirror.version < version <= mirror.version + len(refused):
        # which of the refused batches did the map take? the one subset (in order) whose replay matches
        applied_anyway = version - mirror.version
        for chosen in itertools.combinations(refused, applied_anyway):
            trial = _clone(mirror.map)
            for batch in chosen:
                trial.integrate_batch(batch.laser_scans())
            if np.array_equal(served, trial.risk()):
                mirror.map = trial
                mirror.version = version
                break
        refused.clear()
    if version != mirror.version:
        return False, f"version {version}, {mirror.version} batches acknowledged (no replay matches)", applied_anyway
    if not np.array_equal(served, mirror.map.risk()):
        return False, "risk differs from the replay of the acknowledged batches", applied_anyway
    return True, "ok", applied_anyway


def _clone(m: Any) -> Any:
    return type(m).from_arrays(m.spec, m.sensor, m.to_arrays())


class _Poster:
    """Posts batches on fresh connections (a 500 may close a kept-alive one) and keeps the books."""

    def __init__(self, base_url: str, mirror: Mirror, report: StorageReport) -> None:
        self.client = httpx.Client(base_url=base_url, timeout=60.0, limits=httpx.Limits(max_keepalive_connections=0))
        self.mirror = mirror
        self.report = report
        self.refused: list[Batch] = []

    def post(self, batch: Batch) -> httpx.Response | None:
        try:
            response = batch.post(self.client, self.mirror.name)
        except httpx.HTTPError as exc:
            self.report.other.append(f"connection error instead of an answer: {exc!r}")
            self.refused.append(batch)
            return None
        if response.status_code == 200:
            self.mirror.acked.append((int(response.json()["version"]), batch))
        else:
            self.refused.append(batch)
        return response

    def check(self) -> tuple[bool, str]:
        ok, note, applied = _check_map(self.client, self.mirror, self.refused)
        self.report.refused_but_applied += applied
        self.refused.clear()
        return ok, note

    def close(self) -> None:
        self.client.close()


def storage_faults(seed: int = 1, *, size_bytes: int = 3 * 2**20, max_batches: int = 3000,
                   log: Callable[[str], None] = print) -> StorageReport:
    """Section 2 (full disk) and 3 (read-only directory); the observations."""
    fleet = Fleet.generate(2, 30, seed=seed)
    batches = _batches(fleet)
    volume = Volume.make(size_bytes)
    report = StorageReport(volume.method)
    log(f"data directory: {volume.path} ({volume.method}, {size_bytes / 2**20:.0f} MB)")
    mirror = Mirror("disk", "fuzzy", fleet)
    server = ServerProcess(data_dir=volume.path / "data", env=volume.server_env(), preexec=volume.preexec())
    try:
        server.start()
        poster = _Poster(server.url, mirror, report)
        poster.client.post("/maps", json=fleet.map_request(mirror.name)).raise_for_status()
        # a second map, to be deleted while the disk is full (space freed through the API)
        spare = {**fleet.map_request(mirror.name), "name": "spare"}
        poster.client.post("/maps", json=spare).raise_for_status()
        for batch in batches[:3]:
            batch.post(poster.client, "spare").raise_for_status()
        # ---- fill the disk
        refused: httpx.Response | None = None
        for i in range(max_batches):
            response = poster.post(batches[i % len(batches)])
            if response is None or response.status_code != 200:
                refused = response
                break
        report.disk_full_after = len(mirror.acked)
        if refused is None:
            report.other.append(f"the disk never filled in {max_batches} batches (or the connection broke)")
        else:
            report.disk_full_status = refused.status_code
            report.disk_full_body = refused.text[:300]
            report.disk_full_json_detail = _json_detail(refused)
            log(f"disk full after {report.disk_full_after} batches: {refused.status_code} {refused.text[:160]!r}")
        for i in range(5):  # keep knocking: every answer must stay clean
            response = poster.post(batches[(i + 1) % len(batches)])
            status = response.status_code if response is not None else -1
            report.statuses_while_full[status] = report.statuses_while_full.get(status, 0) + 1
        report.map_intact_while_full, report.map_note_while_full = poster.check()
        deleted = poster.client.delete("/maps/spare")
        report.delete_while_full = f"{deleted.status_code} {deleted.text[:200]}"
        log(f"DELETE of another map while the disk is full: {report.delete_while_full[:160]}")
        # ---- space comes back
        volume.grow(64 * 2**20)
        if volume.method != "tmpfs":
            report.other.append("RLIMIT_FSIZE cannot be raised from outside: recovery checked after restart only")
        response = poster.post(batches[0])
        report.recovered_after_space = response is not None and response.status_code == 200
        report.recovered_status = f"{response.status_code} {response.text[:200]}" if response is not None else "no answer"
        log(f"after the tmpfs grew: {report.recovered_status[:160]}")
        poster.close()
        server.kill()
        # ---- restart: the acknowledged batches are all there
        try:
            server.start()
        except RuntimeError as exc:
            report.restart_after_full_note = f"server did not start: {str(exc)[-300:]}"
            return report
        poster = _Poster(server.url, mirror, report)
        report.restart_after_full_ok, report.restart_after_full_note = poster.check()
        for batch in batches[:3]:
            poster.post(batch)
        poster.close()
        server.kill()
        # ---- the data directory turns read-only (a running server's open files keep the kernel from
        # remounting under it, so the server is restarted on the read-only directory)
        volume.read_only(True)
        try:
            server.start(timeout_s=60.0)
        except RuntimeError as exc:
            lines = [ln for ln in str(exc).splitlines() if ln.strip()]
            report.ro_restart = f"refused to start: {' | '.join(lines[-2:])[-300:]}"
        else:
            poster = _Poster(server.url, mirror, report)
            response = poster.post(batches[3])
            if response is not None:
                report.ro_status, report.ro_body = response.status_code, response.text[:300]
                report.ro_json_detail = _json_detail(response)
            reads = [poster.client.get("/maps/disk"), poster.client.get("/maps/disk/risk", params={"format": "npy"}),
                     poster.client.post("/maps/disk/risk/query", json={"points": [[1.0, 1.0]]})]
            report.ro_reads_ok = all(r.status_code == 200 for r in reads)
            report.ro_restart = (f"started; reads {[r.status_code for r in reads]}; POST scans {report.ro_status} "
                                 f"{report.ro_body[:120]!r}")
            ok, note = poster.check()
            if not ok:
                report.other.append(f"on the read-only directory: {note}")
            poster.close()
            server.kill()
        log(f"restart on the read-only directory: {report.ro_restart}")
        volume.read_only(False)
        server.start()
        poster = _Poster(server.url, mirror, report)
        report.ro_final_ok, report.ro_final_note = poster.check()
        if report.ro_final_ok:
            response = poster.post(batches[5])
            if response is None or response.status_code != 200:
                report.ro_final_ok = False
                report.ro_final_note = "writable again but a batch was refused"
        poster.close()
    finally:
        server.close()
        try:
            volume.read_only(False)
        except (OSError, subprocess.CalledProcessError):
            pass
        volume.cleanup()
    return report


# ---------------------------------------------------------------- replicas on one PostgreSQL

#: The maps of the replica kill loop (name -> model); map i is created through replica i % replicas.
REPLICA_MAPS = {"fz": "fuzzy", "bz": "bayes", "fz2": "fuzzy"}
#: Snapshots every 5 batches: the replicas write them (and drop the log under them) all the time, and a
#: restarted replica loads from a snapshot the other wrote.
REPLICA_ENV = {"FUZZYRISK_SNAPSHOT_EVERY": "5"}
#: The survivor must answer a read of every map within this long after the other replica's kill -9.
SURVIVOR_TARGET_S = 1.0

# Instrumentation of the bench's own database (not of the service): every batch row ever committed,
# with the replica that committed it, and every snapshot written. A snapshot deletes the batch rows it
# covers, so without this the content of an acknowledged batch folded into a snapshot could not be
# compared with what was sent, and a committed but unacknowledged batch could not be replayed.
_AUDIT_SQL = (
    """CREATE TABLE bench_batches (map TEXT NOT NULL, seq BIGINT NOT NULL, payload BYTEA NOT NULL,
        writer TEXT NOT NULL, discarded BOOLEAN NOT NULL DEFAULT false, PRIMARY KEY (map, seq))""",
    """CREATE TABLE bench_snapshots (map TEXT NOT NULL, version BIGINT NOT NULL, writer TEXT NOT NULL)""",
    """CREATE FUNCTION bench_batch_audit() RETURNS trigger LANGUAGE plpgsql AS $$
    BEGIN
        IF TG_OP = 'INSERT' THEN
            INSERT INTO bench_batches (map, seq, payload, writer)
            VALUES (NEW.map, NEW.seq, NEW.payload, current_setting('application_name'));
        ELSIF length(NEW.payload) = 0 AND length(OLD.payload) > 0 THEN
            UPDATE bench_batches SET discarded = true WHERE map = NEW.map AND seq = NEW.seq;
        END IF;
        RETURN NULL;
    END $$""",
    """CREATE FUNCTION bench_snapshot_audit() RETURNS trigger LANGUAGE plpgsql AS $$
    BEGIN
        INSERT INTO bench_snapshots (map, version, writer) VALUES (NEW.map, NEW.version, current_setting('application_name'));
        RETURN NULL;
    END $$""",
    "CREATE TRIGGER bench_batch_audit AFTER INSERT OR UPDATE ON batches FOR EACH ROW EXECUTE FUNCTION bench_batch_audit()",
    ("CREATE TRIGGER bench_snapshot_audit AFTER INSERT OR UPDATE ON snapshots FOR EACH ROW "
     "EXECUTE FUNCTION bench_snapshot_audit()"),
)


def install_audit(database_url: str) -> None:
    """Create the service's tables in ``database_url`` (as a replica's start would) and the bench's audit triggers."""
    import psycopg

    from app.storage.postgres import PostgresStorage

    PostgresStorage(database_url).close()  # the schema, exactly as the service makes it
    with psycopg.connect(database_url, autocommit=True) as conn, conn.transaction():
        for statement in _AUDIT_SQL:
            conn.execute(statement)


@dataclass
class AuditedBatch:
    payload: bytes
    writer: str  # application_name of the replica that committed it
    discarded: bool


def audited(database_url: str, name: str) -> tuple[dict[int, AuditedBatch], list[tuple[int, str]]]:
    """Every batch committed to map ``name`` (version -> row, snapshots or not) and every snapshot written (version, writer)."""
    import psycopg

    with psycopg.connect(database_url, autocommit=True) as conn:
        rows = conn.execute("SELECT seq, payload, writer, discarded FROM bench_batches WHERE map = %s ORDER BY seq",
                            (name,)).fetchall()
        snaps = conn.execute("SELECT version, writer FROM bench_snapshots WHERE map = %s ORDER BY version",
                             (name,)).fetchall()
    return ({int(seq): AuditedBatch(bytes(payload), writer, discarded) for seq, payload, writer, discarded in rows},
            [(int(v), w) for v, w in snaps])


def _array_digest(array: np.ndarray) -> str:
    """The risk grid's values (as float64: a float32 grid and its float64 copy digest alike), shape included."""
    values = np.ascontiguousarray(array, dtype=np.float64)
    return hashlib.sha1(repr(values.shape).encode() + values.tobytes()).hexdigest()


@dataclass(frozen=True)
class RiskRead:
    """One 200 answer of ``GET /maps/{name}/risk?format=npy`` by one replica."""

    name: str
    version: int  # X-Map-Version
    replica: int
    etag: str
    body_digest: str  # sha1 of the .npy bytes
    risk_digest: str  # _array_digest of the grid


@dataclass
class ReplicaKillCounts:
    """The figures of ``replica_kill_loop`` (lists: one entry per kill unless said)."""

    replicas: int = 2
    maps: int = 0
    kills: int = 0
    seconds: float = 0.0
    batches_acked: int = 0
    acked_while_one_down: int = 0  # acknowledged by a survivor while another replica was down
    in_flight: int = 0  # requests cut by a kill (no answer): the client cannot know whether they committed
    in_flight_committed: int = 0  # of them, found committed in the log (kept: served by every replica)
    committed_by: dict[str, int] = field(default_factory=dict)  # replica -> batches it committed
    snapshots_by: dict[str, int] = field(default_factory=dict)  # replica -> snapshots it wrote
    reads_checked: int = 0  # risk reads (any replica, any moment) compared with the replay at their version
    versions_read_by_both: int = 0  # (map, version) read from two replicas or more: compared byte for byte
    survivor_first_read_s: list[float] = field(default_factory=list)  # kill -> the survivor answered a read (one map)
    survivor_read_s: list[float] = field(default_factory=list)  # kill -> the survivor answered a read of every map
    survivor_write_s: list[float] = field(default_factory=list)  # per kill: slowest survivor write under way in the 1 s after
    restart_ready_s: list[float] = field(default_factory=list)  # restart -> /health
    restart_first_read_s: list[float] = field(default_factory=list)  # restarted replica: its first read of every map
    # failures
    acked_lost: int = 0  # acknowledged version missing from the log / a replica, or discarded
    acked_wrong_content: int = 0  # the batch stored under an acknowledged version is not the one sent
    duplicate_versions: int = 0  # one version acknowledged for two batches
    unexplained_versions: int = 0  # committed, never acknowledged, not a batch a kill cut
    version_gaps: int = 0  # a version below the newest with no committed batch
    divergent: int = 0  # (map, version) whose .npy or ETag differs between replicas, or a replica behind at the end
    half_applied: int = 0  # reads whose risk (or scans_fused) differs from the replay of the log up to their version
    store_replay_mismatch: int = 0  # restore(load_map) (snapshot + log) differs from the replay of every batch
    slow_survivor: int = 0  # kills after which the survivor took longer than SURVIVOR_TARGET_S
    server_failed_to_start: int = 0
    unexpected: list[str] = field(default_factory=list)  # non-200 answers, errors outside a kill
    server_log_errors: list[str] = field(default_factory=list)  # level=ERROR records of any replica
    details: list[str] = field(default_factory=list)  # what each failure of the log and replay checks was

    def failures(self) -> int:
        return (self.acked_lost + self.acked_wrong_content + self.duplicate_versions + self.unexplained_versions
                + self.version_gaps + self.divergent + self.half_applied + self.store_replay_mismatch
                + self.slow_survivor + self.server_failed_to_start + len(self.unexpected)
                + len(self.server_log_errors))


class _FleetState:
    """Which replicas take requests (a kill takes one out first), their URLs, and a generation per kill."""

    def __init__(self, urls: list[str]) -> None:
        self.lock = threading.Lock()
        self.urls = list(urls)
        self.up = [True] * len(urls)
        self.generation = [0] * len(urls)

    def pick(self, rng: random.Random) -> tuple[int, str, int]:
        with self.lock:
            i = rng.choice([i for i, up in enumerate(self.up) if up])
            return i, self.urls[i], self.generation[i]

    def down(self, i: int) -> None:
        with self.lock:
            self.up[i] = False
            self.generation[i] += 1

    def back(self, i: int, url: str) -> None:
        with self.lock:
            self.urls[i], self.up[i] = url, True

    def killed_since(self, i: int, generation: int) -> bool:
        with self.lock:
            return self.generation[i] != generation

    def all_up(self) -> bool:
        with self.lock:
            return all(self.up)


@dataclass
class _Book:
    """What the clients saw (thread-safe): acknowledged versions, requests a kill cut, reads, surprises."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    acked: dict[str, dict[int, int]] = field(default_factory=dict)  # map -> version -> batch index
    duplicates: list[str] = field(default_factory=list)
    cut: dict[str, list[int]] = field(default_factory=dict)  # map -> batch indices whose request a kill cut
    reads: list[RiskRead] = field(default_factory=list)
    writes: list[tuple[int, float, float]] = field(default_factory=list)  # (replica, start, end) of each ack
    acked_while_one_down: int = 0
    unexpected: list[str] = field(default_factory=list)

    def ack(self, name: str, version: int, index: int, replica: int, t0: float, t1: float, one_down: bool) -> None:
        with self.lock:
            versions = self.acked.setdefault(name, {})
            if version in versions:
                self.duplicates.append(f"{name} version {version} acknowledged twice")
            versions[version] = index
            self.writes.append((replica, t0, t1))
            self.acked_while_one_down += one_down

    def note(self, message: str) -> None:
        with self.lock:
            self.unexpected.append(message)


def _read_risk(client: httpx.Client, name: str, replica: int) -> tuple[httpx.Response, RiskRead | None]:
    response = client.get(f"/maps/{name}/risk", params={"format": "npy"})
    if response.status_code != 200:
        return response, None
    return response, RiskRead(name, int(response.headers["X-Map-Version"]), replica, response.headers.get("ETag", ""),
                              hashlib.sha1(response.content).hexdigest(), _array_digest(npy_array(response)))


class _Clients:
    """One httpx client per replica URL (a restart moves a replica to a new port); keep-alive shorter than the server's."""

    def __init__(self) -> None:
        self._clients: dict[str, httpx.Client] = {}

    def __call__(self, url: str) -> httpx.Client:
        client = self._clients.get(url)
        if client is None:
            client = self._clients[url] = httpx.Client(base_url=url, timeout=30.0,
                                                       limits=httpx.Limits(keepalive_expiry=2.0))
        return client

    def close(self) -> None:
        for client in self._clients.values():
            client.close()


def _writer(seed: int, offset: int, state: _FleetState, book: _Book, names: list[str], batch_list: list[Batch],
            stop: threading.Event, pause_s: float) -> None:
    """Stream batches, each to a random map through a random replica that is up; keep the books."""
    rng = random.Random(seed)
    clients = _Clients()
    k = offset
    try:
        while not stop.is_set():
            name, index = rng.choice(names), k % len(batch_list)
            k += 1
            i, url, generation = state.pick(rng)
            t0 = time.perf_counter()
            try:
                response = batch_list[index].post(clients(url), name)
            except httpx.ConnectError as exc:  # not sent: nothing can have been stored
                if not state.killed_since(i, generation):
                    book.note(f"replica {i} refused a connection while up: {exc!r}")
                continue
            except httpx.HTTPError as exc:  # sent, no answer: committed or not, the log will tell
                with book.lock:
                    book.cut.setdefault(name, []).append(index)
                if not state.killed_since(i, generation):
                    book.note(f"replica {i} gave no answer to a batch while up: {exc!r}")
                continue
            t1 = time.perf_counter()
            if response.status_code == 200:
                book.ack(name, int(response.json()["version"]), index, i, t0, t1, not state.all_up())
            else:
                book.note(f"replica {i}: batch to {name} answered {response.status_code}: {response.text[:200]}")
            if pause_s:
                time.sleep(pause_s)
    finally:
        clients.close()


def _reader(seed: int, state: _FleetState, book: _Book, names: list[str], stop: threading.Event,
            every_s: float) -> None:
    """Read the risk of a random map through a random replica that is up, every ``every_s``."""
    rng = random.Random(seed)
    clients = _Clients()
    try:
        while not stop.wait(every_s):
            name = rng.choice(names)
            i, url, generation = state.pick(rng)
            try:
                response, read = _read_risk(clients(url), name, i)
            except httpx.HTTPError as exc:
                if not state.killed_since(i, generation):
                    book.note(f"replica {i}: a read of {name} failed while up: {exc!r}")
                continue
            if read is None:
                if not state.killed_since(i, generation):
                    book.note(f"replica {i}: read of {name} answered {response.status_code}: {response.text[:200]}")
                continue
            with book.lock:
                book.reads.append(read)
    finally:
        clients.close()


def _read_every_map(client: httpx.Client, replica: int, names: list[str], book: _Book,
                    deadline_s: float = 60.0, t0: float | None = None) -> list[float]:
    """Read each map's risk through ``client``, in turn, until a 200 (every other answer noted).

    The seconds from ``t0`` (default: now) to each map's 200 (inf: none within ``deadline_s``).
    """
    t0 = time.perf_counter() if t0 is None else t0
    done: list[float] = []
    for name in names:
        while True:
            try:
                response, read = _read_risk(client, name, replica)
            except httpx.HTTPError as exc:
                response, read = None, None
                book.note(f"replica {replica}: a read of {name} failed: {exc!r}")
            if read is not None:
                with book.lock:
                    book.reads.append(read)
                done.append(time.perf_counter() - t0)
                break
            if response is not None:
                book.note(f"replica {replica}: read of {name} answered {response.status_code}: {response.text[:200]}")
            if time.perf_counter() - t0 > deadline_s:
                return done + [math.inf] * (len(names) - len(done))
            time.sleep(0.02)
    return done


def replica_kill_loop(kills: int, *, seed: int, database_url: str, log: Callable[[str], None] = print,
                      replicas: int = 2, writers: int = 3, up_s: tuple[float, float] = (1.0, 3.0),
                      down_s: tuple[float, float] = (0.3, 1.0), pause_s: float = 0.01,
                      read_every_s: float = 0.25) -> ReplicaKillCounts:
    """Replicas on one database, batches to all of them for the same maps, kill -9 of one at a time.

    ``database_url``: an empty database (the bench's audit triggers are installed in it). Between
    kills every replica is up for ``uniform(*up_s)`` s; the killed one (replicas in turn) stays down
    for ``uniform(*down_s)`` s (at least until the survivors answered), then restarts on its data
    directory, reads every map (loads it: snapshot + log) and takes requests again. ``writers``
    threads post batches, each to a random map through a random replica that is up, ``pause_s``
    apart; a reader thread reads a random map's risk through a random replica every ``read_every_s``.
    """
    assert replicas >= 2, "a survivor is needed"
    rng = random.Random(seed)
    fleet = Fleet.generate(2, 40, seed=seed)
    batch_list = _batches(fleet)
    names = list(REPLICA_MAPS)
    counts = ReplicaKillCounts(replicas=replicas, maps=len(names))
    install_audit(database_url)
    procs = Replicas(replicas, database_url, REPLICA_ENV)
    book = _Book()
    stop = threading.Event()
    threads: list[threading.Thread] = []
    kill_times: list[tuple[int, float]] = []  # (victim, time of the kill)
    started = time.perf_counter()
    try:
        procs.start()
        for n, (name, model) in enumerate(REPLICA_MAPS.items()):
            httpx.post(f"{procs.urls[n % replicas]}/maps", json=fleet.map_request(name, model),
                       timeout=30.0).raise_for_status()
        state = _FleetState(procs.urls)
        threads = [threading.Thread(target=_writer, name=f"writer-{w}", daemon=True,
                                    args=(seed * 1000 + w, w * 17, state, book, names, batch_list, stop, pause_s))
                   for w in range(writers)]
        threads.append(threading.Thread(target=_reader, name="reader", daemon=True,
                                        args=(seed * 1000 + 999, state, book, names, stop, read_every_s)))
        for thread in threads:
            thread.start()
        probes = _Clients()
        try:
            for n in range(kills):
                time.sleep(rng.uniform(*up_s))
                victim = n % replicas
                down_for = rng.uniform(*down_s)
                state.down(victim)  # no new request goes to it; those under way are cut by the kill
                t_kill = time.perf_counter()
                procs.kill(victim)
                counts.kills += 1
                kill_times.append((victim, t_kill))
                survivor_s = first_s = 0.0
                for i in range(replicas):
                    if i != victim:
                        times = _read_every_map(probes(procs.urls[i]), i, names, book, t0=t_kill)
                        first_s, survivor_s = max(first_s, times[0]), times[-1]  # every survivor, every map
                counts.survivor_first_read_s.append(first_s)
                counts.survivor_read_s.append(survivor_s)
                time.sleep(max(0.0, t_kill + down_for - time.perf_counter()))  # the survivors take every write
                try:
                    counts.restart_ready_s.append(procs.restart(victim))
                except RuntimeError as exc:
                    counts.server_failed_to_start += 1
                    log(f"kill {n + 1}: replica {victim} did not start again: {str(exc)[-600:]}")
                    break
                first_read = _read_every_map(probes(procs.urls[victim]), victim, names, book)[-1]
                counts.restart_first_read_s.append(first_read)
                state.back(victim, procs.urls[victim])
                with book.lock:
                    acked = sum(len(v) for v in book.acked.values())
                    versions = ", ".join(f"{name}={max(book.acked.get(name, {0: 0}))}" for name in names)
                    cut = sum(len(v) for v in book.cut.values())
                log(f"kill {n + 1:2d} (replica {victim}, {down_for:4.2f} s down): survivor read one map in "
                    f"{first_s:5.3f} s, every map {survivor_s:5.3f} s; restart to ready {counts.restart_ready_s[-1]:4.1f} s, first read of every "
                    f"map {first_read:5.3f} s; acknowledged {acked}, cut by kills {cut}; versions {versions}; "
                    f"unexpected {len(book.unexpected)}")
        finally:
            probes.close()
        stop.set()
        for thread in threads:
            thread.join(timeout=60)
        counts.seconds = time.perf_counter() - started
        _verify_replicas(database_url, procs, names, batch_list, book, counts, kill_times)
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=60)
        counts.server_log_errors = procs.error_lines()
        procs.close()
    return counts


def _verify_replicas(database_url: str, procs: Replicas, names: list[str], batch_list: list[Batch], book: _Book,
                     counts: ReplicaKillCounts, kill_times: list[tuple[int, float]]) -> None:
    """The end of ``replica_kill_loop`` (every writer stopped): the books against the log, the replicas, a replay."""
    from app.maps import logcodec as codec
    from app.storage.postgres import PostgresStorage

    payloads: dict[int, bytes] = {}

    def sent(index: int) -> bytes:
        """Batch ``index`` as the service stores it (``app.maps.logcodec.encode`` of its scans)."""
        if index not in payloads:
            payloads[index] = codec.encode(batch_list[index].laser_scans())
        return payloads[index]

    # final reads: no batch is under way, so every replica catches up with the newest version
    infos: dict[tuple[int, str], dict[str, Any]] = {}
    clients = _Clients()
    try:
        for i, server in enumerate(procs.servers):
            if not server.alive():
                continue
            _read_every_map(clients(server.url), i, names, book)
            for name in names:
                response = clients(server.url).get(f"/maps/{name}")
                if response.status_code == 200:
                    infos[(i, name)] = response.json()
                else:
                    book.note(f"replica {i}: GET /maps/{name} answered {response.status_code}: {response.text[:200]}")
    finally:
        clients.close()
    counts.unexpected = list(book.unexpected)
    counts.duplicate_versions = len(book.duplicates)
    counts.details.extend(book.duplicates)
    counts.batches_acked = sum(len(v) for v in book.acked.values())
    counts.acked_while_one_down = book.acked_while_one_down
    counts.in_flight = sum(len(v) for v in book.cut.values())
    for victim, t_kill in kill_times:  # the slowest survivor write under way in the second after each kill
        spans = [t1 - t0 for replica, t0, t1 in book.writes if replica != victim and t0 <= t_kill + 1.0 and t1 >= t_kill]
        counts.survivor_write_s.append(max(spans, default=0.0))
    counts.slow_survivor = sum(1 for s in counts.survivor_read_s if s > SURVIVOR_TARGET_S)
    storage = PostgresStorage(database_url, max_connections=1)
    try:
        for name in names:
            rows, snapshots = audited(database_url, name)
            _verify_map(name, storage.load_map(name), rows, snapshots, book.acked.get(name, {}),
                        [sent(i) for i in book.cut.get(name, [])], [r for r in book.reads if r.name == name],
                        {i: info for (i, n), info in infos.items() if n == name}, sent, counts)
    finally:
        storage.close()


def _verify_map(name: str, stored: Any, rows: dict[int, AuditedBatch], snapshots: list[tuple[int, str]],
                acked: dict[int, int], cut: list[bytes], reads: list[RiskRead], infos: dict[int, dict[str, Any]],
                sent: Callable[[int], bytes], counts: ReplicaKillCounts) -> None:
    """One map: (a) every acknowledged batch stored as sent, (b) replicas alike, (c) reads = the replay of the log."""
    from collections import Counter

    from app.maps import logcodec as codec
    from app.maps import UNLIMITED_CELLS, build_map, restore

    for _, writer in snapshots:
        counts.snapshots_by[writer] = counts.snapshots_by.get(writer, 0) + 1
    for row in rows.values():
        counts.committed_by[row.writer] = counts.committed_by.get(row.writer, 0) + 1
    if stored is None:
        counts.acked_lost += len(acked)
        counts.details.append(f"{name}: not in the database")
        return
    def as_sent(payload: bytes) -> bytes:
        """A stored batch as its robot sent it: the stamps the service gave its unstamped scans (the time it received
        them) taken off."""
        return codec.encode([scan.stamped(None) for scan in codec.decode_scans(payload)])

    # (a) the log against the books
    in_log = dict(stored.batches)
    for version, index in sorted(acked.items()):
        row = rows.get(version)
        if row is None or row.discarded or version > stored.version or (
                version > stored.snapshot_version and version not in in_log):
            counts.acked_lost += 1
            counts.details.append(f"{name}: acknowledged version {version} is not stored")
        elif as_sent(row.payload) != sent(index) or (version in in_log and in_log[version] != row.payload):
            counts.acked_wrong_content += 1
            counts.details.append(f"{name}: the batch stored as version {version} is not the one acknowledged")
    gaps = sorted(set(range(1, stored.version + 1)) - rows.keys())
    counts.version_gaps += len(gaps)
    if gaps:
        counts.details.append(f"{name}: no batch was committed as version(s) {gaps[:10]}")
    candidates = Counter(cut)
    for version, row in sorted(rows.items()):
        if version in acked or row.discarded:
            continue
        if candidates[as_sent(row.payload)] > 0:  # a batch whose request a kill cut: committed before the replica died
            candidates[as_sent(row.payload)] -= 1
            counts.in_flight_committed += 1
        else:
            counts.unexplained_versions += 1
            counts.details.append(f"{name}: version {version} ({row.writer}) was never acknowledged nor cut by a kill")
    # (c) replay every committed batch in version order, as a replica that never restarted would have
    built = build_map(stored.meta, max_cells=UNLIMITED_CELLS)
    wanted = {read.version for read in reads}
    digest_at: dict[int, str] = {0: _array_digest(built.risk())} if 0 in wanted else {}
    for version, row in sorted(rows.items()):
        if not row.discarded:
            built.integrate_batch(codec.decode(row.payload))
        if version in wanted:
            digest_at[version] = _array_digest(built.risk())
    final = _array_digest(built.risk())
    if _array_digest(restore(stored).map.risk()) != final:
        counts.store_replay_mismatch += 1
        counts.details.append(f"{name}: snapshot {stored.snapshot_version} + log differs from the replay of every batch")
    by_version: dict[int, list[RiskRead]] = {}
    for read in reads:
        by_version.setdefault(read.version, []).append(read)
    for version, group in sorted(by_version.items()):
        counts.reads_checked += len(group)
        if len({read.replica for read in group}) > 1:
            counts.versions_read_by_both += 1
        if len({(read.body_digest, read.etag) for read in group}) > 1:
            counts.divergent += 1
            counts.details.append(f"{name} version {version}: the replicas answered different .npy or ETags "
                                  f"({sorted({(r.replica, r.body_digest[:8], r.etag) for r in group})})")
        bad = [read for read in group if read.risk_digest != digest_at.get(version)]
        if bad:
            counts.half_applied += len(bad)
            counts.details.append(f"{name} version {version}: risk read from replica(s) "
                                  f"{sorted({r.replica for r in bad})} differs from the replay of the log")
    for replica, info in sorted(infos.items()):
        if int(info["version"]) != stored.version:
            counts.divergent += 1
            counts.details.append(f"{name}: replica {replica} is at version {info['version']} after a read, the "
                                  f"database at {stored.version}")
        if int(info["scans_fused"]) != built.scans_fused:
            counts.half_applied += 1
            counts.details.append(f"{name}: replica {replica} says {info['scans_fused']} scans fused, the replay "
                                  f"{built.scans_fused}")


def _fmt(values: list[float], unit: str = "s") -> str:
    """``median / max`` of ``values`` (``n/a`` when there are none)."""
    if not values:
        return "n/a"
    return f"{np.median(values):.3f} / {max(values):.3f} {unit}"


def replicas_main(args: argparse.Namespace) -> int:
    """``--replicas N``: section 4, on a PostgreSQL started here (fsync on) unless ``--database-url`` names one."""
    t0 = time.perf_counter()
    if args.database_url:
        where = "the given database"
        counts = replica_kill_loop(args.kills, seed=args.seed, database_url=args.database_url, replicas=args.replicas)
    else:
        with durable_postgres() as pg:
            where = f"a PostgreSQL {pg.bindir.parent.name} started here, fsync on"
            counts = replica_kill_loop(args.kills, seed=args.seed, database_url=pg.create_database(),
                                       replicas=args.replicas)
    by = ", ".join(f"{w.removeprefix('fuzzyrisk-replica-')}: {n}" for w, n in sorted(counts.committed_by.items()))
    snaps = ", ".join(f"{w.removeprefix('fuzzyrisk-replica-')}: {n}" for w, n in sorted(counts.snapshots_by.items()))
    print(f"\nreplicas: {counts.replicas} on one database ({where}), {counts.maps} maps written through every "
          f"replica; {counts.kills} kills in {time.perf_counter() - t0:.0f} s; {counts.batches_acked} batches "
          f"acknowledged ({counts.acked_while_one_down} by a survivor while the other was down); committed by "
          f"replica {by}; snapshots written by replica {snaps}; {counts.in_flight} requests cut by a kill, "
          f"{counts.in_flight_committed} of them committed (kept, served by every replica); {counts.reads_checked} "
          f"risk reads checked, {counts.versions_read_by_both} (map, version) read from both replicas")
    print(f"  survivor answered a read after the kill: of one map {_fmt(counts.survivor_first_read_s)}, of every map "
          f"in turn {_fmt(counts.survivor_read_s)} (median / max; target {SURVIVOR_TARGET_S:.0f} s)")
    print(f"  slowest survivor write under way in the second after a kill: {_fmt(counts.survivor_write_s)}")
    print(f"  killed replica: restart to ready {_fmt(counts.restart_ready_s)}; then its first read of every map "
          f"(load: snapshot + log) {_fmt(counts.restart_first_read_s)}")
    rows = [
        ("acknowledged batches lost", counts.acked_lost),
        ("acknowledged batches stored with other content", counts.acked_wrong_content),
        ("versions acknowledged twice", counts.duplicate_versions),
        ("committed versions neither acknowledged nor cut by a kill", counts.unexplained_versions),
        ("version gaps in the log", counts.version_gaps),
        ("divergent replicas ((map, version) read differently, or behind at the end)", counts.divergent),
        ("half-applied (reads != replay of the log at their version)", counts.half_applied),
        ("snapshot + log != replay of every batch", counts.store_replay_mismatch),
        (f"kills after which the survivor took > {SURVIVOR_TARGET_S:.0f} s", counts.slow_survivor),
        ("replica failed to start", counts.server_failed_to_start),
        ("unexpected answers (5xx, 4xx, errors outside a kill)", len(counts.unexpected)),
        ("ERROR records in the replicas' logs", len(counts.server_log_errors)),
    ]
    for label, value in rows:
        print(f"  {'PASS' if value == 0 else 'FAIL'}  {label}: {value}")
    for line in [*counts.details[:10], *counts.unexpected[:10], *counts.server_log_errors[:10]]:
        print(f"        {line}")
    return 1 if counts.failures() > 0 or counts.kills < args.kills else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--skip-storage", action="store_true", help="only the kill -9 part")
    parser.add_argument("--replicas", type=int, default=0,
                        help="N >= 2: section 4 only, N replicas on one PostgreSQL, kill -9 of one at a time")
    parser.add_argument("--database-url", default="",
                        help="with --replicas: an empty PostgreSQL database to use (default: start a cluster)")
    args = parser.parse_args(argv)
    print(f"machine: {machine()}")
    if args.replicas:
        if args.replicas < 2:
            parser.error("--replicas needs at least 2 (a survivor)")
        return replicas_main(args)
    t0 = time.perf_counter()
    counts = kill_loop(args.kills, args.seed)
    ready = counts.kill_to_ready_s
    print(f"\nkill -9: {counts.kills} kills in {time.perf_counter() - t0:.0f} s, {counts.batches_acked} batches "
          f"acknowledged, {counts.batches_in_flight} in flight at a kill, {counts.in_flight_committed} of them "
          f"committed (kept, as the version said); restart to ready {np.median(ready) if ready else float('nan'):.1f} s "
          f"median, {max(ready) if ready else float('nan'):.1f} s max")
    rows = [
        ("acknowledged batches lost", counts.acked_lost),
        ("maps that failed to load", counts.maps_failed_to_load),
        ("server failed to start", counts.server_failed_to_start),
        ("half-applied batches", counts.half_applied),
        ("risk != replay of acknowledged batches", counts.risk_mismatches),
        ("version jumps", counts.version_jumps),
        ("other errors", len(counts.other_errors)),
    ]
    for label, value in rows:
        print(f"  {'PASS' if value == 0 else 'FAIL'}  {label}: {value}")
    for err in counts.other_errors[:5]:
        print(f"        {err}")
    for err in counts.server_log_errors[:5]:
        print(f"        server log: {err}")
    failed = counts.failures() > 0 or counts.kills < args.kills
    if not args.skip_storage:
        print()
        report = storage_faults(args.seed)
        print(f"\nfull disk ({report.method}): refused after {report.disk_full_after} batches with "
              f"{report.disk_full_status}; answers while full {report.statuses_while_full}; refused but applied: "
              f"{report.refused_but_applied}; map as acknowledged: {report.map_note_while_full}; recovered once "
              f"space was back: {report.recovered_after_space}; restart: {report.restart_after_full_note}")
        print(f"read-only ({report.method}): {report.ro_restart}; writable again: {report.ro_final_note}")
        problems = report.failures()
        for p in problems:
            print(f"  FAIL  {p}")
        if not problems:
            print("  PASS  full disk and read-only directory: clean 5xx, no corruption")
        failed = failed or bool(problems)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
