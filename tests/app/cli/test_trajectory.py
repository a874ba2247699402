"""``python -m app.import_log --trajectory``: a corrected log's poses put on a map, and its rebuild waited for."""

from __future__ import annotations

import gzip
import http.server
import json
import math
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import httpx
import pytest

from app.cli.import_log import main
from app.schemas import MapCreate
from fuzzyocc.carmen import read_carmen
from tests.conftest import ROOT, carmen_log


@pytest.fixture
def orebro() -> Path:
    return carmen_log("orebro-corrected.log.gz")


class _Refusion(http.server.BaseHTTPRequestHandler):
    """A stand-in service with one map, ``m`` in frame ``robot1/map``, that takes a trajectory and rebuilds it one
    step a read of its progress (``steps`` reads), or answers ``refuse`` to the PUT, or fails, or is superseded."""

    requests: ClassVar[list[tuple[str, str]]] = []
    puts: ClassVar[list[dict[str, Any]]] = []
    steps: ClassVar[int] = 3
    total: ClassVar[int] = 1000
    refuse: ClassVar[tuple[int, dict[str, Any]] | None] = None
    ending: ClassVar[str] = "done"  # or "failed", or "superseded"
    reads: ClassVar[int] = 0

    def log_message(self, *args: Any) -> None:  # keep the test output clean
        pass

    def _answer(self, status: int, body: dict[str, Any]) -> None:
        data = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    @classmethod
    def status(cls, state: str, done: int, **fields: Any) -> dict[str, Any]:
        return {"state": state, "id": "c0ffee", "requested": "2026-12-07T13:00:00Z", "from_version": 8,
                "scans_reposed": 237, "scans_done": done, "scans_total": cls.total, "elapsed_s": 0.1 * done,
                "eta_s": None, "version": None, "error": None, **fields}

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        self.requests.append(("GET", self.path))
        if self.path == "/maps/m":
            self._answer(200, {"name": "m", "frame_id": "robot1/map", "version": 8})
        elif self.path == "/maps/m/rebuild":
            cls = type(self)
            cls.reads += 1
            if cls.reads < cls.steps:
                self._answer(200, self.status("running", cls.total * cls.reads // cls.steps))
            elif cls.ending == "failed":
                self._answer(200, self.status("failed", cls.total // 2, error="the disk is full"))
            elif cls.ending == "superseded":
                self._answer(200, self.status("running", 0, id="beef"))
            else:
                self._answer(200, self.status("done", cls.total, version=9))
        else:
            self._answer(404, {"code": "NOT_FOUND", "message": f"no map at {self.path}", "details": None})

    def do_PUT(self) -> None:  # noqa: N802
        self.requests.append(("PUT", self.path))
        self.puts.append(json.loads(self.rfile.read(int(self.headers["Content-Length"]))))
        if self.refuse is not None:
            self._answer(*self.refuse)
        else:
            self._answer(202, {"rebuild": self.status("running", 0)})


@pytest.fixture
def service() -> Iterator[type[_Refusion]]:
    """The stand-in's URL is its ``url``; its state is fresh for each test."""

    class Service(_Refusion):
        requests, puts = [], []

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Service)
    Service.url = f"http://127.0.0.1:{server.server_address[1]}"  # type: ignore[attr-defined]
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield Service
    server.shutdown()
    server.server_close()
    thread.join(timeout=10)


def run_command(*args: str) -> subprocess.CompletedProcess[str]:
    """The command as a user runs it, in its own process (which ends before this returns)."""
    return subprocess.run([sys.executable, "-m", "app.import_log", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=240)


def put(log: Path, service: type[_Refusion], *options: str) -> int:
    return main(["--trajectory", str(log), "--url", service.url, "--map", "m", *options])  # type: ignore[attr-defined]


def test_the_logs_stamps_and_laser_poses_are_put_and_the_rebuild_is_waited_for(
        orebro: Path, service: type[_Refusion], capsys: pytest.CaptureFixture[str]) -> None:
    assert put(orebro, service) == 0
    out, err = capsys.readouterr()
    assert service.requests == [("GET", "/maps/m"), ("PUT", "/maps/m/trajectory")] + [("GET", "/maps/m/rebuild")] * 3
    [path] = service.puts
    scans = read_carmen(orebro)
    assert path["header"]["frame_id"] == "robot1/map"  # the map's own frame
    assert len(path["poses"]) == len(scans) == 237
    # the log's stamps are all 0: numbered at 5 Hz, as its import numbered them
    assert [p["header"]["stamp"] for p in path["poses"]] == [
        {"sec": k // 5, "nanosec": k % 5 * 200_000_000} for k in range(237)]
    for pose, scan in zip(path["poses"], scans, strict=True):
        x, y, theta = scan.pose
        assert pose["header"]["frame_id"] == "robot1/map"
        assert pose["pose"]["position"] == {"x": x, "y": y, "z": 0.0}
        q = pose["pose"]["orientation"]
        assert (q["x"], q["y"]) == (0.0, 0.0) and math.atan2(q["z"], q["w"]) * 2 == pytest.approx(theta, abs=1e-12)
    assert sum("numbered at 5 Hz" in line for line in err.splitlines()) == 1
    last = [line for line in err.splitlines() if line.startswith("fuzzyrisk-import-log: rebuilding: ")][-1]
    assert re.fullmatch(r"fuzzyrisk-import-log: rebuilding: 1,000/1,000 scans; [\d.,]+ scans/s, \d\d:\d\d elapsed, "
                        r"00:00 left", last), last
    assert len(out.splitlines()) == 1
    assert "237 poses put on map 'm'" in out and "237 scans re-posed" in out
    assert "the map rebuilt from 1,000 scans" in out and "version 9" in out


def test_with_no_wait_the_command_returns_once_the_correction_is_held(
        orebro: Path, service: type[_Refusion], capsys: pytest.CaptureFixture[str]) -> None:
    assert put(orebro, service, "--no-wait") == 0
    assert service.requests == [("GET", "/maps/m"), ("PUT", "/maps/m/trajectory")]
    out = capsys.readouterr().out
    assert "237 scans re-posed" in out and "rebuilt in the background (correction c0ffee" in out


def test_a_refused_trajectory_exits_1_with_the_services_message(
        orebro: Path, service: type[_Refusion], capsys: pytest.CaptureFixture[str]) -> None:
    service.refuse = (409, {"code": "CONFLICT", "message": "no stored scan has a stamp in the path's range",
                            "details": None})
    assert put(orebro, service) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == (f"fuzzyrisk-import-log: error: PUT {service.url}/maps/m/trajectory answered 409: "  # type: ignore[attr-defined]
                       "CONFLICT: no stored scan has a stamp in the path's range")
    assert ("GET", "/maps/m/rebuild") not in service.requests


@pytest.mark.parametrize(("ending", "said"), [
    ("failed", "the rebuild of 'm' failed: the disk is full"),
    ("superseded", "the correction c0ffee of 'm' was superseded by beef before its rebuild finished"),
])
def test_a_rebuild_that_fails_or_is_superseded_exits_1_saying_so(
        orebro: Path, service: type[_Refusion], capsys: pytest.CaptureFixture[str], ending: str, said: str) -> None:
    service.ending = ending
    assert put(orebro, service) == 1
    out, err = capsys.readouterr()
    assert out == "" and f"fuzzyrisk-import-log: error: {said}" in err.splitlines()[-1]


def test_a_missing_map_exits_1_naming_it(orebro: Path, service: type[_Refusion],
                                         capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--trajectory", str(orebro), "--url", service.url, "--map", "other"]) == 1  # type: ignore[attr-defined]
    assert "answered 404: NOT_FOUND" in capsys.readouterr().err
    assert service.puts == []


@pytest.mark.parametrize("options", [
    ["--trajectory", "x.log"],                                          # no service
    ["--trajectory", "x.log", "--url", "http://127.0.0.1:8000"],       # no map
    ["x.log", "--trajectory", "x.log", "--url", "http://127.0.0.1:8000", "--map", "m"],  # a LOG too
    ["--trajectory", "x.log", "--url", "http://127.0.0.1:8000", "--map", "m", "--npy", "x.npy"],
    ["--trajectory", "x.log", "--url", "http://127.0.0.1:8000", "--map", "m", "--every", "2"],
    ["x.log", "--no-wait"],
    [],
])
def test_options_that_do_not_go_with_a_trajectory_are_refused(
        options: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(options)
    assert info.value.code == 2
    assert "error:" in capsys.readouterr().err


def _first_scans(log: Path, count: int, out: Path, drift: float = 0.0) -> Path:
    """The first ``count`` FLASER lines of ``log`` as a log of their own; with ``drift``, their laser poses drift from
    the first scan on (a growing offset and turn, as odometry drifts) and their beams and stamps stay."""
    with gzip.open(log, "rt") as lines:
        scans = [line.split() for line in lines if line.startswith("FLASER")][:count]
    for k, fields in enumerate(scans):
        at = 2 + int(fields[1])  # x y theta follow the ranges
        x, y, theta = (float(v) for v in fields[at:at + 3])
        fields[at:at + 3] = [repr(x + 0.01 * drift * k), repr(y - 0.006 * drift * k), repr(theta + 0.002 * drift * k)]
    out.write_text("".join(" ".join(fields) + "\n" for fields in scans))
    return out


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_through_a_real_service_a_drifted_map_corrected_by_the_original_log_is_the_original_map(
        orebro: Path, tmp_path: Path) -> None:
    from bench._client import ServerProcess

    original = _first_scans(orebro, 100, tmp_path / "original.log")
    drifted = _first_scans(orebro, 100, tmp_path / "drifted.log", drift=1.0)
    server = ServerProcess(data_dir=tmp_path / "data")
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            assert run_command(str(original), "--url", server.url, "--map", "direct").returncode == 0
            # the drifted log's own bounds would make another grid: it goes into a map of the direct one's box
            box = {k: v for k, v in client.get("/maps/direct").json().items() if k in MapCreate.model_fields}
            assert client.post("/maps", json={**box, "name": "drifted"}).status_code == 201
            imported = run_command(str(drifted), "--url", server.url, "--map", "drifted", "--append")
            assert imported.returncode == 0, imported.stderr
            direct = client.get("/maps/direct/risk", params={"format": "npy"}).content
            assert client.get("/maps/drifted/risk", params={"format": "npy"}).content != direct
            version = client.get("/maps/drifted").json()["version"]

            corrected = run_command("--trajectory", str(original), "--url", server.url, "--map", "drifted")
            assert corrected.returncode == 0, corrected.stderr
            assert "rebuilding: 100/100 scans" in corrected.stderr
            assert "100 poses put on map 'drifted'" in corrected.stdout
            assert "100 scans re-posed" in corrected.stdout and f"version {version + 1}" in corrected.stdout
            assert client.get("/maps/drifted/risk", params={"format": "npy"}).content == direct
            poses = [p["pose"] for p in client.get("/maps/drifted/trajectory").json()["poses"]]
            assert poses == [p["pose"] for p in client.get("/maps/direct/trajectory").json()["poses"]]

            # another building's log: its stamps (2002's) span none of the map's scans, and the service says so
            other = run_command("--trajectory", str(carmen_log("seattle-corrected.log.gz")), "--url", server.url,
                                "--map", "drifted")
            assert other.returncode == 1
            [said] = [line for line in other.stderr.splitlines() if "error" in line]
            assert said.startswith(f"fuzzyrisk-import-log: error: PUT {server.url}/maps/drifted/trajectory answered "
                                   "409: "), said
            assert client.get("/maps/drifted").json()["version"] == version + 1  # nothing changed
    finally:
        server.close()
