"""Starting and stopping: a port in use, the directories chosen, readiness, children that die with their parent."""

from __future__ import annotations

import gc
import importlib.metadata
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil
import pytest
from fastapi.testclient import TestClient

from app.config import Settings
from app.ops import process_setup
from app.ops.process_setup import StartupError, prepare_directories
from tests.conftest import ROOT


def _wait_ready(client: TestClient, timeout_s: float = 120.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        answer = client.get("/ready")
        if answer.status_code == 200 or time.monotonic() > deadline:
            return {"status_code": answer.status_code, **answer.json()}
        assert answer.status_code == 503 and answer.headers["Retry-After"] == "1", answer.text
        time.sleep(0.05)


def _distribution(requirement: str) -> str:
    """The normalised distribution name a requirement (or a ``constraints.txt`` line) is about."""
    return re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9._-]+", requirement).group(0)).lower()  # type: ignore[union-attr]


# ---------------------------------------------------------------- the start


def test_a_port_in_use_stops_the_start_at_once_with_exit_1_and_a_message(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        started = time.monotonic()
        result = subprocess.run(
            [sys.executable, "-m", "app", "--port", str(port), "--data-dir", str(tmp_path / "data")],
            cwd=ROOT, capture_output=True, text=True, timeout=60,
        )
    assert result.returncode == 1, result.stderr
    assert f"port {port} on 127.0.0.1 is already in use" in result.stderr and "FUZZYRISK_PORT" in result.stderr
    assert time.monotonic() - started < 10  # before the maps, the kernels or the workers
    assert not (tmp_path / "data").exists()  # nothing created


#: ``sitecustomize.py`` of a Python as without an extra: the path finder finds none of the ``HIDDEN`` modules, so
#: ``importlib.util.find_spec`` answers None for them, as where they were never installed.
WITHOUT_MODULES = """
import importlib.machinery
import sys

HIDDEN = {hidden!r}


class WithoutHidden(importlib.machinery.PathFinder):
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        return None if name.partition(".")[0] in HIDDEN else super().find_spec(name, path, target)


sys.meta_path[:] = [WithoutHidden if finder is importlib.machinery.PathFinder else finder for finder in sys.meta_path]
"""


@pytest.mark.parametrize(("variable", "value", "hidden", "extra"), [
    ("FUZZYRISK_DATABASE_URL", "postgresql://fleet@127.0.0.1:5432/maps", "psycopg", "postgres"),
    ("FUZZYRISK_DATABASE_URL", "postgresql://fleet@127.0.0.1:5432/maps", "psycopg_pool", "postgres"),
    ("FUZZYRISK_FOXGLOVE_PORT", "8765", "foxglove", "foxglove"),
])
def test_a_setting_whose_extra_is_not_installed_stops_the_start_before_anything_with_exit_2_and_one_line(
    tmp_path: Path, variable: str, value: str, hidden: str, extra: str,
) -> None:
    site = tmp_path / "site"  # on PYTHONPATH: its sitecustomize runs as the interpreter starts
    site.mkdir()
    (site / "sitecustomize.py").write_text(WITHOUT_MODULES.format(hidden={hidden}))
    env = {**os.environ, "PYTHONPATH": str(site), variable: value}
    look_up = f"import importlib.util; print(importlib.util.find_spec({hidden!r}))"
    hides = subprocess.run([sys.executable, "-c", look_up], check=False, env=env, capture_output=True, text=True,
                           timeout=60)
    assert hides.stdout == "None\n", hides.stderr  # the module is out of sight, and nothing else
    with socket.socket() as taken:  # the service's port, held here: a start that got as far as binding says so
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run(
            [sys.executable, "-m", "app", "--port", str(port), "--data-dir", str(tmp_path / "data")],
            check=False, cwd=ROOT, env=env, capture_output=True, text=True, timeout=60,
        )
    assert result.returncode == 2, result.stderr
    said = (f"python -m app: {variable} needs {hidden}, which is not installed: pip install 'fuzzyrisk[{extra}]' "
            f"(an image: docker build --build-arg EXTRAS={extra}), or unset {variable}")
    assert result.stderr.splitlines() == [said]
    assert result.stdout == "" and not (tmp_path / "data").exists()  # nothing bound, logged or created


def test_with_its_extra_installed_a_setting_starts_no_such_check() -> None:
    settings = Settings(database_url="postgresql://fleet@127.0.0.1:5432/maps", foxglove_port=8765)
    assert process_setup.missing_extra(settings) is None  # this environment has every extra (the test one)
    assert process_setup.missing_extra(Settings()) is None


def test_each_setting_that_needs_an_extra_names_one_of_pyproject_that_installs_its_modules() -> None:
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    installed_by = importlib.metadata.packages_distributions()  # import name -> distributions

    assert {extra.setting for extra in process_setup.EXTRAS} <= set(Settings.model_fields)
    for extra in process_setup.EXTRAS:
        wanted = {_distribution(requirement) for requirement in extras[extra.name]}
        for module in extra.modules:
            assert {_distribution(d) for d in installed_by[module]} & wanted, (extra.name, module)


def test_the_listening_socket_says_it_is_tcp_so_that_answers_are_not_delayed() -> None:
    """asyncio sets TCP_NODELAY only on connections of a socket whose protocol is IPPROTO_TCP: without it, a
    small answer waits for the client's delayed ACK (a /health of 40-50 ms instead of a few)."""
    sock = process_setup.bind("127.0.0.1", 0)
    with sock:
        assert sock.proto == socket.IPPROTO_TCP and sock.type == socket.SOCK_STREAM


def test_a_bad_setting_stops_the_start_with_exit_1_naming_it(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "app", "--data-dir", str(tmp_path / "data")], cwd=ROOT,
                            env={**os.environ, "FUZZYRISK_PLAN_WORKERS": "0"}, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 1 and "plan_workers" in result.stderr, result.stderr


def test_the_web_process_imports_no_planner_kernel() -> None:
    """Plans run in the workers: the server must not compile their kernels (seconds on a cold cache)."""
    code = "import sys, app.api.factory; print(' '.join(sorted(m for m in sys.modules if m.startswith('planning'))))"
    loaded = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    kernels = [m for m in loaded.split() if m.startswith("planning._") and m.endswith("_kernels")]
    assert kernels == [] and "planning.query" not in loaded.split(), loaded


def _blas_process(**env: str) -> list[str]:
    """The OPENBLAS_NUM_THREADS and the thread count of a process that limited BLAS's threads, then multiplied."""
    code = ("import os; from app.ops.process_setup import limit_blas_threads; limit_blas_threads(); import numpy; "
            "numpy.ones((200_000, 3)) @ numpy.ones((3, 3)); "
            "print(os.environ['OPENBLAS_NUM_THREADS'], len(os.listdir('/proc/self/task')))")
    base = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True,
                          env={**base, **env}).stdout.split()


def test_blas_runs_in_the_calling_thread_unless_the_environment_says_otherwise() -> None:
    # OpenBLAS's own threads took 22-41 ms of CPU per lidar cloud beside the fusion and parse threads
    assert _blas_process() == ["1", "1"]
    assert _blas_process(OPENBLAS_NUM_THREADS="2")[0] == "2"


def test_the_kernel_cache_goes_to_the_data_directory_unless_numba_cache_dir_says(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR")  # restored at the end of the test, whatever the code sets
    monkeypatch.setenv("TMPDIR", os.environ.get("TMPDIR", tempfile.gettempdir()))
    chosen = prepare_directories(Settings(data_dir=tmp_path / "data"))
    assert chosen.numba_cache == (tmp_path / "data" / "numba-cache").resolve() and chosen.numba_cache.is_dir()
    assert os.environ["NUMBA_CACHE_DIR"] == str(chosen.numba_cache) and chosen.warning is None
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "elsewhere"))
    assert prepare_directories(Settings(data_dir=tmp_path / "data")).numba_cache == (tmp_path / "elsewhere").resolve()


def test_an_unusable_cache_directory_falls_back_to_a_temporary_one_with_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setenv("TMPDIR", os.environ.get("TMPDIR", tempfile.gettempdir()))
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "numba-cache").write_text("a file where the cache would go")
    chosen = prepare_directories(Settings(data_dir=tmp_path / "data"))
    assert chosen.warning is not None and "every start compiles them" in chosen.warning
    assert chosen.numba_cache.is_dir() and chosen.numba_cache != (tmp_path / "data" / "numba-cache").resolve()
    chosen.numba_cache.rmdir()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "data" / "numba-cache"))  # set by the user: no fallback
    with pytest.raises(StartupError, match="NUMBA_CACHE_DIR"):
        prepare_directories(Settings(data_dir=tmp_path / "data"))


def test_an_uncreatable_data_directory_stops_the_start(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    with pytest.raises(StartupError, match="FUZZYRISK_DATA_DIR"):
        prepare_directories(Settings(data_dir=tmp_path / "file" / "data"))


def test_without_a_writable_temporary_directory_the_data_directory_holds_the_temporary_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A read-only root: multiprocessing's sockets need a writable directory."""
    monkeypatch.setenv("TMPDIR", os.environ.get("TMPDIR", tempfile.gettempdir()))
    monkeypatch.setattr(tempfile, "tempdir", None)

    def nowhere() -> str:
        raise FileNotFoundError("No usable temporary directory found")

    monkeypatch.setattr(tempfile, "gettempdir", nowhere)
    (tmp_path / "data" / "tmp" / "pymp-stale").mkdir(parents=True)  # what a killed run left
    temp = process_setup._ensure_temp_dir(tmp_path / "data" / "tmp")
    assert temp == (tmp_path / "data" / "tmp").resolve() and os.environ["TMPDIR"] == str(temp)
    assert list(temp.iterdir()) == []


# ---------------------------------------------------------------- readiness


def test_ready_answers_503_then_200_once_the_kernels_are_compiled(make_client: Callable[..., TestClient]) -> None:
    client = make_client(api_key="k" * 16)  # /ready needs no key, as /health
    ready = _wait_ready(client)
    assert ready == {"status_code": 200, "status": "ready", "maps_loaded": 0, "maps_quarantined": [],
                     "kernels_compiled": True, "planner_workers_ready": 0, "planner_workers_wanted": 0,
                     "batches_in_line": 0, "longest_fusion_job_s": 0.0, "detail": ""}


def test_once_ready_a_full_garbage_collection_skips_what_lives_as_long_as_the_process(
    make_settings: Callable[..., Settings], monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a full collection walked every module, kernel and map of the process (about 100 ms on 175,000
    # objects, holding the GIL): every client's requests waited, at the collector's rhythm
    from app.api.factory import create_app
    from app.service import mapservice

    monkeypatch.setattr(mapservice, "gc", gc)  # the collector itself, as in the service's own process

    with TestClient(create_app(make_settings())) as client:
        _wait_ready(client)
        assert gc.get_freeze_count() > 10_000
    assert gc.get_freeze_count() == 0  # a stopped service leaves the collector as it found it


def test_ready_waits_for_the_planner_workers_when_they_start_with_the_service(
    make_client: Callable[..., TestClient],
) -> None:
    client = make_client(plan_warmup=True, plan_workers=2)
    ready = _wait_ready(client)
    assert ready["status_code"] == 200, ready
    assert ready["planner_workers_ready"] == 2 and ready["planner_workers_wanted"] == 2
    assert "/ready" in client.get("/openapi.json").json()["paths"]


# ---------------------------------------------------------------- children that end with their parent


def test_die_with_parent_ends_a_child_when_its_parent_is_killed(tmp_path: Path) -> None:
    if not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux's")
    armed = tmp_path / "armed"
    child = ("import pathlib, time; from app.ops.process_setup import die_with_parent; assert die_with_parent(); "
             f"pathlib.Path({str(armed)!r}).write_text('1'); time.sleep(120)")
    parent = subprocess.Popen([sys.executable, "-c", (
        "import subprocess, sys, time; "
        f"subprocess.Popen([sys.executable, '-c', {child!r}]); time.sleep(120)")], cwd=ROOT)
    try:
        deadline = time.monotonic() + 30
        while not armed.exists():
            assert time.monotonic() < deadline and parent.poll() is None
            time.sleep(0.05)
        (orphan,) = psutil.Process(parent.pid).children()
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
    _, alive = psutil.wait_procs([orphan], timeout=5)
    assert not alive


def test_the_forkserver_preload_does_nothing_outside_a_forkserver() -> None:
    import app.ops.forkserver_preload

    assert app.ops.forkserver_preload.ACTIVE is False  # this process must not die with pytest's parent


# ---------------------------------------------------------------- the lock


def test_constraints_pin_every_dependency_of_every_extra() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        wanted += extra

    pinned = {_distribution(line): line for line in (ROOT / "constraints.txt").read_text().splitlines()
              if line and not line.startswith("#")}
    assert all("==" in line for line in pinned.values())
    assert sorted({_distribution(r) for r in wanted} - set(pinned)) == []


def test_a_lower_priority_is_lower_than_where_the_thread_ran_started_niced_or_not() -> None:
    # relative: a service started at niceness 10 (nice, systemd's Nice=) set its workers to 5, above itself
    import threading

    def niced_then_lowered() -> tuple[int, int]:
        me = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, me, os.getpriority(os.PRIO_PROCESS, me) + 3)
        before = os.getpriority(os.PRIO_PROCESS, me)
        process_setup.lower_priority(5)
        return before, os.getpriority(os.PRIO_PROCESS, me)

    result: list[tuple[int, int]] = []
    thread = threading.Thread(target=lambda: result.append(niced_then_lowered()))
    thread.start()
    thread.join()
    before, after = result[0]
    assert after == min(19, before + 5)
