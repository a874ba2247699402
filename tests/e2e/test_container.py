"""The Dockerfile's steps without a Docker engine: its layout, its HEALTHCHECK and CMD run for real, and the
service on a read-only root (a mount namespace, as ``docker run --read-only -v volume:/data`` gives)."""

from __future__ import annotations

import fnmatch
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest

from app.plans.pool import SHUTDOWN_GRACE_S
from tests.conftest import carmen_log
from tests.e2e.conftest import CHILDREN_GRACE_S, ROOT, assert_ended, free_port

pytestmark = pytest.mark.slow

DOCKERFILE = (Path(__file__).resolve().parents[2] / "Dockerfile").read_text()
#: docker stop's default wait between SIGTERM and SIGKILL.
DOCKER_STOP_S = 10.0
SITE_PACKAGES = "/opt/fuzzyrisk/lib/python3.11/site-packages"


def _exec_form(instruction: str) -> list[str]:
    """The JSON array of the last ``instruction [..]`` (continuation lines joined)."""
    text = DOCKERFILE.replace("\\\n", " ")
    (match,) = re.findall(rf"^{instruction}\b.*?(\[.*\])\s*$", text, flags=re.MULTILINE)[-1:]
    return list(json.loads(match))


def _stage(index: int) -> str:
    return re.split(r"^FROM ", DOCKERFILE, flags=re.MULTILINE)[index + 1]


def test_the_image_is_built_in_two_stages_from_a_pinned_base_with_locked_dependencies_first() -> None:
    (base,) = re.findall(r"^ARG PYTHON_IMAGE=(\S+)$", DOCKERFILE, flags=re.MULTILINE)
    assert re.fullmatch(r"python:3\.11\.\d+-slim-bookworm@sha256:[0-9a-f]{64}", base)
    assert re.findall(r"^FROM (\S+)", DOCKERFILE, flags=re.MULTILINE) == ["${PYTHON_IMAGE}", "${PYTHON_IMAGE}"]
    build, final = _stage(0), _stage(1)
    # the dependencies' layer comes before any source, and installs the locked versions
    assert build.index("COPY pyproject.toml constraints.txt") < build.index("COPY app")
    assert build.index("--constraint constraints.txt --requirement") < build.index("COPY app")
    assert "pip uninstall --yes pip setuptools" in build
    # the final image: no pip or setuptools, a non-root user owning /data, tini as PID 1
    assert "pip uninstall --yes --no-cache-dir pip setuptools wheel" in final and "COPY --from=build /opt/fuzzyrisk" in final
    assert re.search(r"^USER (?!root)\S+$", final, flags=re.MULTILINE)
    assert 'VOLUME ["/data"]' in final and "FUZZYRISK_DATA_DIR=/data" in final and "EXPOSE 8000" in final
    assert _exec_form("ENTRYPOINT") == ["/usr/bin/tini", "--"]
    assert _exec_form("CMD") == ["python", "-m", "app", "--host", "0.0.0.0"]
    assert "curl" not in final.split("HEALTHCHECK", 1)[1]


def _trim_step() -> str:
    """The build stage's RUN that trims the environment (continuation lines joined)."""
    build = _stage(0).replace("\\\n", " ")
    (trim,) = [line for line in build.splitlines() if line.startswith(f"RUN cd {SITE_PACKAGES}")]
    return trim


def _trimmed_paths() -> list[str]:
    """What the trim step's ``rm -rf`` commands remove: globs relative to site-packages."""
    paths: list[str] = []
    for command in _trim_step().split("&&"):
        words = command.split()
        if words[:2] == ["rm", "-rf"]:
            paths += words[2:]
    return paths


#: Imports the service and does the work that loads more than its imports (a PNG, MCAP chunks compressed both
#: ways, a dilation by the robot, a rotated cloud, a TF lookup between samples, the ROS type stores), then prints
#: every file it loaded: the modules' files, and the shared libraries mapped into the process (the dependencies of
#: the extension modules among them).
_LOADED = """
import io, json, sys
import app.api.factory, app.plans.worker, app.cli.import_bag, app.ros.messages_in, app.reads.recording, app.ros.messages_out, app.ros.bagsize, app.formats.exports
import fuzzyocc, planning.query
import numpy as np
from PIL import Image
from mcap.writer import CompressionType, Writer
from rosbags.typesys import Stores, get_typestore
from fuzzyocc.scans import PointCloud
from fuzzyocc.tf import Transform, TransformBuffer
from planning import RiskField
from planning.packed import PackedGrid
Image.fromarray(np.zeros((4, 4), np.uint8)).save(io.BytesIO(), format="PNG")
for compression in (CompressionType.ZSTD, CompressionType.LZ4):
    writer = Writer(io.BytesIO(), compression=compression)
    writer.start()
    channel = writer.register_channel("/t", "cdr", writer.register_schema("s", "ros2msg", b""))
    writer.add_message(channel, log_time=0, data=bytes(1000), publish_time=0)
    writer.finish()
PackedGrid(RiskField(np.zeros((5, 5)), 0.1, (0.0, 0.0)), 0.1, 0.5, False, 1.0).eroded_valid_flat()
PointCloud.from_sensor_frame(np.ones((2, 3)), (0.0, 0.0, 0.0), (0.1, 0.2, 0.3, 0.9), range_max=5.0)
buffer = TransformBuffer()
for stamp, yaw in ((0, 0.0), (10, 0.5)):
    buffer.add("map", "laser", stamp, Transform.of((stamp, 0.0, 0.0), (0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2))))
buffer.lookup("map", "laser", 3)
get_typestore(Stores.ROS2_JAZZY), get_typestore(Stores.ROS1_NOETIC)
files = {getattr(m, "__file__", None) for m in list(sys.modules.values())} - {None}
files |= {line.split()[-1] for line in open("/proc/self/maps") if ".so" in line}
print(json.dumps(sorted(files)))
"""


def test_the_environment_is_trimmed_in_the_build_stage_of_nothing_the_service_loads() -> None:
    """An image of at most 500 MB: the build stage removes what the service never loads, after the
    dependencies and before the sources, so the final image never gets it; and none of it is what the service
    loads, here with the same locked versions: no module, no shared library, nothing under a test suite."""
    build = _stage(0)
    trim = build.index(f"RUN cd {SITE_PACKAGES}")
    assert build.index("--constraint constraints.txt --requirement") < trim < build.index("COPY app")
    step = _trim_step()
    # every shared library stripped, but one that strip breaks (ldd refuses the stripped copy) kept whole
    assert "strip --strip-unneeded" in step and 'ldd "$f.stripped"' in step
    # the build fails if a trim went too far for the service's imports
    assert re.search(r"python -I -c \s*\"import app\.api\.factory, app\.plans\.worker, app\.cli\.import_bag, planning\.query\"",
                     build[build.index("COPY app"):].replace("\\\n", " "))
    removed = _trimmed_paths()
    assert len(removed) > 20 and "numpy/distutils" in removed and "numba/cuda" in removed
    # scipy in the image for its rotations: what they load survives the trim (checked below with the rest)
    project = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())["project"]
    assert [d for d in project["dependencies"] if re.match(r"scipy\b", d)]
    result = subprocess.run([sys.executable, "-c", _LOADED], capture_output=True, text=True, timeout=600,
                            cwd=Path(__file__).resolve().parents[2])
    assert result.returncode == 0, result.stderr
    loaded = [f.split("site-packages/", 1)[1] for f in json.loads(result.stdout) if "site-packages/" in f]
    assert any(f.startswith("pillow.libs/") for f in loaded)
    assert any(f.startswith("scipy/spatial/transform/") for f in loaded)
    hits = [(f, p) for f in loaded for p in removed if fnmatch.fnmatch(f, p) or f.startswith(p.rstrip("/") + "/")]
    assert not hits, hits
    assert not [f for f in loaded if "/tests/" in f"/{f}" or f.endswith((".pyi", ".pxd", ".pyx", ".pxi", ".a"))]


def test_a_stop_fits_in_docker_stop() -> None:
    assert re.search(r"^STOPSIGNAL SIGTERM$", DOCKERFILE, flags=re.MULTILINE)
    (graceful,) = re.findall(r"FUZZYRISK_GRACEFUL_TIMEOUT_S=(\d+)", DOCKERFILE)
    # requests in flight, then the planner workers; what is left is for the snapshots
    assert float(graceful) + SHUTDOWN_GRACE_S <= DOCKER_STOP_S - 3


def test_the_healthcheck_command_passes_against_a_ready_server_and_fails_without(start_server: Any) -> None:
    command = _exec_form("HEALTHCHECK.*CMD")
    assert command[0] == "python" and "/ready" in command[-1]
    server = start_server()  # returns once /ready answers 200
    env = {**os.environ, "FUZZYRISK_PORT": str(server.port)}
    assert subprocess.run([sys.executable, *command[1:]], env=env, timeout=30).returncode == 0
    server.stop()
    failed = subprocess.run([sys.executable, *command[1:]], env=env, timeout=30, capture_output=True)
    assert failed.returncode != 0


def _mount_namespaces() -> bool:
    if not sys.platform.startswith("linux") or shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "--mount", "--propagation", "private", "true"], capture_output=True)
    return probe.returncode == 0


@pytest.mark.skipif(not _mount_namespaces(), reason="needs a mount namespace (unshare --mount, as root)")
def test_the_service_starts_and_serves_on_a_read_only_root(tmp_path: Path) -> None:
    """Everything read-only but the data directory, no writable home or /tmp, the kernel cache cold: the first
    start of a container with ``--read-only``. The service keeps its kernels and temporary files in /data."""
    data = tmp_path / "data"
    data.mkdir()
    port = free_port()
    script = (
        f"mount --bind {data} {data} && mount -o remount,bind,ro / "
        "&& if touch /.fuzzyrisk-probe 2>/dev/null; then exit 99; fi "  # the root must really be read-only
        f"&& cd {data} && exec {sys.executable} -m app --port {port}"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(HOME="/nonexistent", FUZZYRISK_DATA_DIR=str(data), FUZZYRISK_PLAN_WORKERS="2")
    log_path = tmp_path / "server.log"
    with log_path.open("wb") as log:
        process = subprocess.Popen(["unshare", "--mount", "--propagation", "private", "sh", "-c", script],
                                   env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        url = f"http://127.0.0.1:{port}"
        with httpx.Client(base_url=url, timeout=120.0) as client:
            deadline = time.monotonic() + 300
            while True:  # until it answers: its kernels compile for tens of seconds after
                assert process.poll() is None, log_path.read_text()
                assert time.monotonic() < deadline, log_path.read_text()
                try:
                    if client.get("/health").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                time.sleep(0.2)
            # a log imported at once, as the README's first steps do: the importer says the service is compiling
            # and its first batch waits for the kernels
            imported = subprocess.run(
                [sys.executable, "-m", "app.import_log", str(carmen_log("orebro-corrected.log.gz")), "--every", "8",
                 "--url", url, "--map", "orebro"], cwd=ROOT, capture_output=True, text=True, timeout=300)
            assert imported.returncode == 0, imported.stderr + log_path.read_text()
            assert (f"fuzzyrisk-import-log: the service at {url} is still compiling its fusion kernels (its first "
                    "start); the first batch waits for them...") in imported.stderr.splitlines()
            assert "237 scans read, 30 fused, 207 skipped" in imported.stdout
            while True:
                assert process.poll() is None, log_path.read_text()
                assert time.monotonic() < deadline, log_path.read_text()
                if client.get("/ready").status_code == 200:
                    break
                time.sleep(0.2)
            assert client.post("/maps", json={"name": "lab", "resolution": 0.1, "origin": [-5, -5],
                                              "size": [10, 10]}).status_code == 201
            scan = {"pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": -0.5, "angle_increment": 0.1,
                    "ranges": [3.0] * 11, "range_min": 0.1, "range_max": 10}
            assert client.post("/maps/lab/scans", json={"scans": [scan]}).status_code == 200
            for space, start, goal in (("R2", [-3, -3], [3, -3]), ("SE2", [-3, -3, 0], [3, -3, 0])):
                planned = client.post("/maps/lab/plan", json={"start": start, "goal": goal, "state_space": space,
                                                              "planner": "RRTConnect", "time_limit": 1.0})
                assert planned.status_code == 200 and planned.json()["status"] == "exact", planned.text
        assert any((data / "numba-cache").rglob("*.nbi")) and (data / "tmp").is_dir()
        children = psutil.Process(process.pid).children(recursive=True)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) in (0, -signal.SIGTERM), log_path.read_text()
        assert_ended(children, CHILDREN_GRACE_S)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=30)
