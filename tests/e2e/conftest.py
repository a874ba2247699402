"""End-to-end fixtures: a real server process on loopback, and a small simulated world to scan.

The world is a 10 m x 6 m hall split by a wall at x = 5 m with a 1.2 m door; a robot's
LaserScan is computed by ray/box intersection against the true walls (slab method,
vectorized over beams and boxes).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil
import pytest
from playwright.sync_api import Browser, Page, expect, sync_playwright

import dev

ROOT = Path(__file__).resolve().parents[2]

# Walls as axis-aligned boxes [xmin, ymin, xmax, ymax] (metres, map frame).
DOOR = (2.4, 3.6)  # y-extent of the door in the middle wall
WALLS = np.array([
    [0.0, 0.0, 10.0, 0.2],     # south
    [0.0, 5.8, 10.0, 6.0],     # north
    [0.0, 0.0, 0.2, 6.0],      # west
    [9.8, 0.0, 10.0, 6.0],     # east
    [4.9, 0.2, 5.1, DOOR[0]],  # middle wall, below the door
    [4.9, DOOR[1], 5.1, 5.8],  # middle wall, above the door
])
WORLD_MAP = {"name": "hall", "dimensions": 2, "resolution": 0.05, "origin": [0.0, 0.0], "size": [10.0, 6.0],
             "model": "fuzzy", "sensor": {"range_sigma": 0.02, "registration_sigma": 0.0}}
POSES = [(x, y, th) for x in (1.5, 3.5, 6.5, 8.5) for y in (1.5, 3.0, 4.5) for th in (0.0, 2.0)] + [
    (4.2, 3.0, 0.0), (5.8, 3.0, 3.14), (5.0, 3.0, 1.57)]
BEAMS = 720
RANGE_MAX = 12.0
#: The most a test waits for a condition it needs (a server ready, a message, a page's state): a net against
#: a hang, far beyond what a busy machine takes. Tests wait for the condition, never for this long.
PATIENCE_S = 240.0
# Playwright's assertions wait for their condition up to 5 s by default: the page's work shares a busy machine too
expect.set_options(timeout=PATIENCE_S * 1000)


def scan_ranges(x: float, y: float, theta: float, beams: int = BEAMS) -> np.ndarray:
    """Ranges of a 360-degree LaserScan from (x, y, theta) to the nearest wall; +inf for no hit."""
    angles = theta - np.pi + np.arange(beams) * (2 * np.pi / beams)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)[:, None, :]  # (B, 1, 2)
    lo, hi = WALLS[None, :, :2], WALLS[None, :, 2:]                     # (1, W, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - [x, y]) / d, (hi - [x, y]) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=2)
    t_far = np.nanmin(np.maximum(t1, t2), axis=2)
    hit = (t_near <= t_far) & (t_far > 0)
    t = np.where(hit, np.maximum(t_near, 0.0), np.inf).min(axis=1)
    return np.where(t <= RANGE_MAX, t, np.inf)


def laser_json(pose: tuple[float, float, float], beams: int = BEAMS) -> dict[str, Any]:
    ranges = scan_ranges(*pose, beams=beams)
    return {"pose": {"x": pose[0], "y": pose[1], "theta": pose[2]}, "angle_min": -np.pi,
            "angle_increment": 2 * np.pi / beams, "range_min": 0.05, "range_max": RANGE_MAX,
            "ranges": ["inf" if np.isinf(r) else round(float(r), 4) for r in ranges]}


def distance_to_walls(points: np.ndarray) -> np.ndarray:
    """Euclidean distance from each (N, 2) point to the nearest wall box (0 inside one)."""
    p = points[:, None, :]
    gap = np.maximum(np.maximum(WALLS[None, :, :2] - p, p - WALLS[None, :, 2:]), 0.0)
    return np.hypot(gap[..., 0], gap[..., 1]).min(axis=1)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Server:
    """``python -m app`` in its own process on loopback."""

    data_dir: Path
    env: dict[str, str] = field(default_factory=dict)
    port: int = 0
    process: subprocess.Popen[bytes] | None = None
    log_path: Path | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = PATIENCE_S) -> Server:
        """Start and wait until ``/ready`` answers 200 (maps loaded, kernels compiled, planner workers up)."""
        self.port = free_port()
        # one planner process, started at the first plan unless a test asks for the warm-up
        env = {**os.environ, "FUZZYRISK_PLAN_WORKERS": "1", "FUZZYRISK_PLAN_WARMUP": "false",
               "FUZZYRISK_DISK_RESERVE_BYTES": str(64 * 1024), **self.env}
        self.data_dir.parent.mkdir(parents=True, exist_ok=True)
        self.log_path = self.data_dir.parent / f"server-{self.port}.log"
        log = self.log_path.open("wb")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "app", "--port", str(self.port), "--data-dir", str(self.data_dir)],
            cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited with {self.process.returncode}:\n{self.log()}")
            try:
                if httpx.get(f"{self.url}/ready", timeout=1.0).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"server was not ready within {timeout_s} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path else ""

    def client(self, timeout_s: float = 60.0) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=timeout_s)

    def children(self) -> list[psutil.Process]:
        """The server's processes: planner forkserver and workers, multiprocessing's resource tracker."""
        assert self.process is not None
        try:
            return psutil.Process(self.process.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            return []

    def terminate(self, timeout_s: float = 60.0) -> int:
        """SIGTERM (graceful: requests in flight finish, maps are snapshotted); the exit code, once every
        process the server started has ended too."""
        assert self.process is not None
        children = self.children()
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(timeout=timeout_s)
        assert_ended(children, CHILDREN_GRACE_S)
        return code

    def kill(self) -> None:
        """SIGKILL: no chance to flush anything; the server's children must still end (checked)."""
        assert self.process is not None
        children = self.children()
        self.process.kill()
        self.process.wait(timeout=30)
        assert_ended(children, CHILDREN_GRACE_S)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.kill()


#: Seconds a killed server's children may take to end (the issue's bar: none alive 10 s later).
CHILDREN_GRACE_S = 10.0


def assert_ended(processes: list[psutil.Process], timeout_s: float) -> None:
    """Every one of ``processes`` ends within ``timeout_s`` (the stragglers are killed, then the test fails)."""
    _, alive = psutil.wait_procs(processes, timeout=timeout_s)
    alive = [p for p in alive if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    for process in alive:
        process.kill()
    assert not alive, f"still alive {timeout_s:.0f} s after the server ended: {[p.pid for p in alive]}"


@pytest.fixture
def start_server(tmp_path: Path) -> Iterator[Callable[..., Server]]:
    """Start servers on ``tmp_path/data`` (the same directory each time: restarts see the same maps)."""
    servers: list[Server] = []

    def start(**env: str) -> Server:
        server = Server(tmp_path / "data", env=env).start()
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.stop()


class World:
    """The simulated world, handed to tests as the ``world`` fixture."""

    MAP = WORLD_MAP
    POSES = POSES
    DOOR = DOOR
    RANGE_MAX = RANGE_MAX
    scan_ranges = staticmethod(scan_ranges)
    laser_json = staticmethod(laser_json)
    distance_to_walls = staticmethod(distance_to_walls)


@pytest.fixture
def world() -> type[World]:
    return World


# ---------------------------------------------------------------- headless Chromium (Debian's)


def find_chromium() -> str:
    """The Chromium to drive: $CHROME, else ``chromium`` or ``chromium-browser`` on the PATH (``dev.find_chromium``)."""
    found = dev.find_chromium()
    if found is None:
        named = os.environ.get("CHROME")
        pytest.fail(f"no Chromium found ({'CHROME=' + named if named else 'chromium, chromium-browser'} on the "
                    "PATH): `python3 dev.py test` installs Debian's chromium, or set CHROME to a Chromium executable",
                    pytrace=False)
    return found


CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=find_chromium(), args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser: Browser) -> Iterator[Page]:
    """A fresh 1280 x 900 page; the test fails if the page raised a JavaScript error."""
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    yield pg
    context.close()
    assert not errors, f"JavaScript errors on the page: {errors}"
