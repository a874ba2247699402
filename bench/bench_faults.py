"""Crash and storage faults: kill -9 at random moments, a full disk, a read-only data directory.

    python -m bench.bench_faults [--kills 20] [--seed 1] [--skip-storage]   (from the repository root)

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
"""

from __future__ import annotations

import argparse
import itertools
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
              max_delay_s: float = 1.5) -> KillCounts:
    """Stream batches and kill -9 the server ``kills`` times; the counts of section 1."""
    rng = random.Random(seed)
    fleet = Fleet.generate(2, 40, seed=seed)
    batches = _batches(fleet)
    mirrors = {name: Mirror(name, model, fleet) for name, model in MAPS.items()}
    counts = KillCounts()
    server = ServerProcess(env=FAULT_ENV)
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--skip-storage", action="store_true", help="only the kill -9 part")
    args = parser.parse_args(argv)
    print(f"machine: {machine()}")
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
