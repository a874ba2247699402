"""``python -m app.import_log``: a recorded log becomes a map in-process and through a real service, the same bit for bit."""

from __future__ import annotations

import gzip
import http.server
import io
import json
import os
import pty
import re
import socket
import struct
import subprocess
import sys
import termios
import threading
import zipfile
from fcntl import ioctl
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml
from PIL import Image

from app.cli.import_log import main
from fuzzyocc import FuzzyMap
from fuzzyocc.carmen import grid_for_scans, read_carmen
from tests.conftest import ROOT, carmen_log



@pytest.fixture
def orebro() -> Path:
    """The smallest recorded log (237 scans), from tests/data; the test fails, not skips, without it."""
    return carmen_log("orebro-corrected.log.gz")


def run_command(*args: str) -> subprocess.CompletedProcess[str]:
    """The command as a user runs it, in its own process (which ends before this returns)."""
    return subprocess.run([sys.executable, "-m", "app.import_log", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=240)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_in_process_writes_a_png_a_nav2_zip_and_the_risk_of_the_library_map(
        orebro: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    png, nav2, npy = tmp_path / "orebro.png", tmp_path / "orebro.zip", tmp_path / "orebro.npy"
    code = main([str(orebro), "--every", "4", "--png", str(png), "--nav2", str(nav2), "--npy", str(npy)])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "237 scans read, 60 fused, 177 skipped (--every 4)" in out and len(out.splitlines()) == 1
    assert "fuzzyrisk-import-log: fusing: 60/60 scans, " in err

    scans = read_carmen(orebro)[::4]
    spec = grid_for_scans(scans, 0.05, 1.0)
    expected = FuzzyMap(spec)
    expected.integrate_batch(scans)
    risk = np.load(npy)
    assert risk.dtype == np.float32 and np.array_equal(risk, expected.risk())
    assert f"{spec.shape[0]} x {spec.shape[1]} cells" in out

    with Image.open(png) as image:
        assert image.size == spec.shape and image.mode == "RGB"  # one pixel a cell, x to the right
        pixels = np.asarray(image)
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 10  # walls, free space and unknown, not one flat colour

    with zipfile.ZipFile(nav2) as archive:
        meta = yaml.safe_load(archive.read("map.yaml"))
        with Image.open(io.BytesIO(archive.read(meta["image"]))) as grey:
            assert grey.size == spec.shape
            levels = set(np.unique(np.asarray(grey)).tolist())
    assert meta["resolution"] == 0.05 and meta["origin"] == [spec.origin[0], spec.origin[1], 0.0]
    assert {0, 255} <= levels  # occupied walls and free corridors


def test_a_first_run_says_it_compiles_and_its_progress_lines_give_total_and_rate(orebro: Path,
                                                                               tmp_path: Path) -> None:
    cold = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}  # as on a machine never run on
    first, second = (subprocess.run([sys.executable, "-m", "app.import_log", str(orebro), "--every", "8"], check=False,
                                    cwd=ROOT, capture_output=True, text=True, timeout=600, env=cold)
                     for _ in range(2))
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    compiling = "fuzzyrisk-import-log: compiling the fusion kernels (first run only: numba caches them for later runs)..."
    assert first.stderr.splitlines().count(compiling) == 1
    assert compiling not in second.stderr  # loaded from the cache the first run filled
    for run in (first, second):  # stderr is a pipe: plain lines, the last one with the whole stage
        last = [line for line in run.stderr.splitlines() if line.startswith("fuzzyrisk-import-log: fusing: ")][-1]
        assert re.fullmatch(r"fuzzyrisk-import-log: fusing: 30/30 scans, [\d,]+ rays; [\d.,]+ scans/s, "
                            r"\d\d:\d\d elapsed, 00:00 left", last), last


def test_on_a_terminal_the_progress_is_a_bar(orebro: Path) -> None:
    leader, follower = pty.openpty()
    ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    with subprocess.Popen([sys.executable, "-m", "app.import_log", str(orebro), "--every", "4"], cwd=ROOT,
                          stdout=subprocess.PIPE, stderr=follower, text=True) as process:
        os.close(follower)  # the child's copy is the only one left: reading ends when it exits
        shown = b""
        while True:
            try:
                chunk = os.read(leader, 65536)
            except OSError:  # EIO: the child closed the terminal
                break
            if not chunk:
                break
            shown += chunk
        out = process.stdout.read() if process.stdout else ""
    os.close(leader)
    assert process.returncode == 0, shown.decode()
    assert "60 fused" in out  # the summary still goes to stdout, alone
    screens = [s for s in re.split(r"[\r\n]+", shown.decode()) if s.startswith("fuzzyrisk-import-log: fusing:")]
    assert "100%|" in screens[-1] and "60/60" in screens[-1] and "scans/s" in screens[-1]


def test_a_malformed_log_exits_non_zero_naming_the_line(tmp_path: Path) -> None:
    log = tmp_path / "bad.log"
    log.write_text("ODOM 0 0 0 0 0 0 1 h 1\nFLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 1 h 1\nFLASER 3 1.0 oops 3.0 0 0 0 0 0 0 1 h 1\n")
    result = run_command(str(log), "--png", str(tmp_path / "out.png"))
    assert result.returncode == 1
    assert "line 3" in result.stderr and "'oops'" in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "out.png").exists()


def test_a_missing_log_exits_non_zero_saying_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path / "nowhere.log.gz")]) == 1
    assert "nowhere.log.gz: no such file" in capsys.readouterr().err


def test_an_unreachable_service_exits_non_zero_saying_so(orebro: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    assert main([str(orebro), "--every", "50", "--url", url, "--map", "orebro"]) == 1
    assert f"cannot reach the service at {url}" in capsys.readouterr().err


@pytest.mark.parametrize("options", [["--url", "http://127.0.0.1:8000"], ["--map", "m"], ["--every", "0"],
                                     ["--png", "/no/such/dir/x.png"],
                                     ["--nav2", "x.zip", "--nav2-mode", "scale"]])  # scale PGM: no unknown
def test_inconsistent_options_are_refused_before_reading(orebro: Path, options: list[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([str(orebro), *options])
    assert info.value.code == 2


class _BusyOnce(http.server.BaseHTTPRequestHandler):
    """A stand-in service whose first scan batch meets a full line (503, Retry-After), then is taken."""

    posts: list[str] = []
    bodies: list[dict[str, Any]] = []

    def log_message(self, *args: Any) -> None:  # keep the test output clean
        pass

    def _answer(self, status: int, body: dict[str, Any], headers: dict[str, str] | None = None) -> None:
        data = json.dumps(body).encode()
        self.send_response(status)
        for key, value in {"Content-Type": "application/json", "Content-Length": str(len(data)),
                           **(headers or {})}.items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(data)

    def do_POST(self) -> None:  # noqa: N802 (http.server's name)
        scans = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        self.posts.append(self.path)
        self.bodies.append(scans)
        if self.path == "/maps":
            self._answer(201, {"name": scans["name"], "model": "fuzzy", "version": 0})
        elif self.posts.count(self.path) == 1:
            self._answer(503, {"code": "UNAVAILABLE", "message": "map busy: 32 batches in line",
                                "details": None}, {"Retry-After": "0.2"})
        elif len(scans["scans"]) > 4:
            self._answer(413, {"code": "TOO_LARGE", "message": "too many scans in one batch (FUZZYRISK_MAX_SCANS_PER_BATCH)",
                                "details": None})
        else:
            self._answer(200, {"scans_fused": len(scans["scans"]), "rays": 1, "version": len(self.posts)})


@pytest.fixture
def busy_service() -> Iterator[str]:
    _BusyOnce.posts, _BusyOnce.bodies = [], []
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _BusyOnce)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()
    thread.join(timeout=10)


def test_a_busy_service_is_waited_for_and_other_errors_show_its_detail(
        orebro: Path, busy_service: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(orebro), "--every", "30", "--batch", "4", "--url", busy_service, "--map", "m"]) == 0
    assert _BusyOnce.posts == ["/maps"] + ["/maps/m/scans"] * 3  # 8 scans in 2 batches, the first sent twice
    sent = [r for body in _BusyOnce.bodies[2:] for scan in body["scans"] for r in scan["ranges"]]
    assert len(sent) == 8 * 181 and "inf" in sent  # no-returns travel as "inf" (JSON has no infinity)
    assert all(r == "inf" or isinstance(r, float) for r in sent)
    capsys.readouterr()
    assert main([str(orebro), "--every", "30", "--batch", "8", "--url", busy_service, "--map", "m"]) == 1
    err = capsys.readouterr().err
    assert "answered 413: TOO_LARGE: too many scans in one batch (FUZZYRISK_MAX_SCANS_PER_BATCH)" in err
    assert "0 of 8 scans were fused into 'm'" in err


def test_the_scans_are_posted_with_their_log_stamps(busy_service: str, capsys: pytest.CaptureFixture[str]) -> None:
    seattle = carmen_log("seattle-corrected.log.gz")  # stamps that increase: posted as logged, to the nanosecond
    assert main([str(seattle), "--every", "60", "--batch", "4", "--url", busy_service, "--map", "m"]) == 0
    stamps = [scan["header"]["stamp"] for body in _BusyOnce.bodies[2:] for scan in body["scans"]]
    with gzip.open(seattle, "rt") as lines:
        logged = [line.split()[-1] for line in lines if line.startswith("FLASER")][::60]
    assert stamps == [{"sec": int(t.split(".")[0]), "nanosec": int(t.split(".")[1].ljust(9, "0"))} for t in logged]
    assert "numbered" not in capsys.readouterr().err


def test_a_log_whose_stamps_do_not_increase_is_posted_at_5_hz_and_said_so(
        orebro: Path, busy_service: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(orebro), "--every", "30", "--batch", "4", "--url", busy_service, "--map", "m"]) == 0
    stamps = [scan["header"]["stamp"] for body in _BusyOnce.bodies[2:] for scan in body["scans"]]
    assert stamps == [{"sec": 6 * k, "nanosec": 0} for k in range(8)]  # every 30th scan of 5 Hz: 6 s apart
    said = [line for line in capsys.readouterr().err.splitlines() if "stamps" in line]
    assert len(said) == 1 and said[0].startswith("fuzzyrisk-import-log: orebro-corrected.log.gz: ")
    assert "numbered at 5 Hz" in said[0]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_through_a_real_service_the_risk_equals_the_in_process_map_bit_for_bit(orebro: Path, tmp_path: Path) -> None:
    from bench._client import ServerProcess

    local = tmp_path / "local.npy"
    assert main([str(orebro), "--npy", str(local), "--png", str(tmp_path / "local.png")]) == 0
    # the suite's kernel cache: a service on a machine it never ran on (a cold cache, the command's line while it
    # compiles) is test_container.py's read-only start, which runs this command first
    server = ServerProcess(data_dir=tmp_path / "data")
    server.start()
    try:
        remote = [str(orebro), "--url", server.url, "--map", "orebro"]
        result = run_command(*remote, "--png", str(tmp_path / "remote.png"), "--nav2", str(tmp_path / "remote.zip"))
        assert result.returncode == 0, result.stderr
        assert "237 scans read, 237 fused, 0 skipped" in result.stdout
        assert "map 'orebro' version 8 on" in result.stdout  # 237 scans in batches of 32
        assert sum("numbered at 5 Hz" in line for line in result.stderr.splitlines()) == 1  # its stamps are all 0
        path = httpx.get(f"{server.url}/maps/orebro/trajectory", timeout=60).json()
        assert [p["header"]["stamp"] for p in path["poses"]] == [
            {"sec": k // 5, "nanosec": k % 5 * 200_000_000} for k in range(237)]
        assert [(p["pose"]["position"]["x"], p["pose"]["position"]["y"]) for p in path["poses"]] == [
            s.pose[:2] for s in read_carmen(orebro)]

        response = httpx.get(f"{server.url}/maps/orebro/risk", params={"format": "npy"}, timeout=60)
        assert response.status_code == 200
        served = np.load(io.BytesIO(response.content), allow_pickle=False)
        assert served.dtype == np.float32 and np.array_equal(served, np.load(local))
        with Image.open(tmp_path / "remote.png") as a, Image.open(tmp_path / "local.png") as b:
            assert np.array_equal(np.asarray(a), np.asarray(b))
        with zipfile.ZipFile(tmp_path / "remote.zip") as archive:
            assert yaml.safe_load(archive.read("map.yaml"))["resolution"] == 0.05

        again = run_command(*remote, "--every", "100")
        assert again.returncode == 1
        assert "a map named 'orebro' exists" in again.stderr and "--append" in again.stderr
        appended = run_command(*remote, "--every", "100", "--append")
        assert appended.returncode == 0, appended.stderr
        info = httpx.get(f"{server.url}/maps/orebro", timeout=30).json()
        assert info["scans_fused"] == 237 + 3 and info["version"] == 9
    finally:
        server.close()
