"""Suite-wide: one numba cache for every process the tests start, and no process left behind.

* ``NUMBA_CACHE_DIR`` (unless set) is ``.numba-cache`` at the repository's root, for this process
  and every server a test starts: each compiles a kernel at most once per checkout, as a service
  restarted on its data directory does. The tests of a cold start take a new, empty one.
* Every process a test starts inherits ``SESSION_MARK`` in its environment; when the session ends,
  any such process still alive (``kill -9`` of a server that left its planner workers behind, a
  server a test forgot) fails the run, and is ended.
"""

from __future__ import annotations

import gzip
import multiprocessing.forkserver
import multiprocessing.resource_tracker
import os
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import psutil
import pytest

from tests.pgserver import postgres_server  # noqa: F401 - a real PostgreSQL, for the tests that ask

ROOT = Path(__file__).resolve().parents[1]
#: The real data the tests read, part of the repository (``tests/data/README.md``: where each file comes from).
DATA_DIR = ROOT / "tests" / "data"
SESSION_MARK = "FUZZYRISK_TEST_SESSION"
#: How long processes of the session may take to end once the tests are done (as after a kill -9 of a server).
STRAGGLER_GRACE_S = 10.0

os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))
os.environ[SESSION_MARK] = uuid.uuid4().hex


def _own_helpers() -> set[int]:
    """This process's multiprocessing forkserver and resource tracker: they end with it (the forkserver is
    killed by Linux when this process ends, the tracker when its last client has gone)."""
    pids = {getattr(multiprocessing.forkserver._forkserver, "_forkserver_pid", None),
            getattr(multiprocessing.resource_tracker._resource_tracker, "_pid", None)}
    return {pid for pid in pids if pid is not None}


def session_processes() -> list[psutil.Process]:
    """Live processes started during this session (they carry its mark), other than this one and its helpers."""
    mark, me, helpers = os.environ[SESSION_MARK], os.getpid(), _own_helpers()
    found = []
    for process in psutil.process_iter():
        if process.pid == me or process.pid in helpers:
            continue
        try:
            if process.status() != psutil.STATUS_ZOMBIE and process.environ().get(SESSION_MARK) == mark:
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
    return found


@pytest.fixture(scope="session", autouse=True)
def no_process_outlives_the_suite() -> Iterator[None]:
    """Fail the run if any process a test started is still alive once the tests are done (then end it)."""
    yield
    deadline = time.monotonic() + STRAGGLER_GRACE_S
    strays = session_processes()
    while strays and time.monotonic() < deadline:
        time.sleep(0.2)
        strays = session_processes()
    if not strays:
        return
    described = []
    for process in strays:
        try:
            described.append(f"{process.pid} (parent {process.ppid()}): {' '.join(process.cmdline())[:200]}")
            process.kill()
        except psutil.Error:
            continue
    pytest.fail(f"{len(strays)} process(es) started by the tests outlived them by {STRAGGLER_GRACE_S:.0f} s "
                "(ended now):\n" + "\n".join(described))


def error_message(response) -> str:  # type: ignore[no-untyped-def]
    """The human-readable message of an error answer (every error body is ``{code, message, details}``)."""
    return str(response.json()["message"])


def carmen_log(name: str) -> Path:
    """A recorded CARMEN log of ``tests/data/carmen`` (e.g. ``orebro-corrected.log.gz``, the smallest: 237 scans);
    fails (never skips) when it is not there, as the logs are part of the repository."""
    path = DATA_DIR / "carmen" / name
    if not path.is_file():
        pytest.fail(f"{path} is missing: the CARMEN logs the tests read are kept in the repository under "
                    "tests/data/carmen (see tests/data/README.md); restore them from git")
    return path


def ouster_frames() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The three OS-1-128 frames of ``tests/data/ouster``: ``(points, rotation, translation)`` each, the points in the
    sensor frame (no-return rows dropped), the pose of the sensor in the first frame's frame (``R @ p + t``)."""
    folder = DATA_DIR / "ouster"
    if not (folder / "poses.txt").is_file():
        pytest.fail(f"{folder} is missing: the Ouster frames the tests read are kept in the repository")
    poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    frames = []
    for i, pose in enumerate(poses):
        raw = np.frombuffer(gzip.decompress((folder / f"{i:06d}.bin.gz").read_bytes()), dtype=np.float32)
        points = raw.reshape(-1, 4)[:, :3].astype(np.float64)
        frames.append((points[np.any(points != 0.0, axis=1)], pose[:, :3], pose[:, 3]))
    return frames
