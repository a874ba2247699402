"""The Dockerfile's steps without a Docker engine: its HEALTHCHECK command and its CMD, run for real."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.slow

DOCKERFILE = (Path(__file__).resolve().parents[2] / "Dockerfile").read_text()


def _exec_form(instruction: str) -> list[str]:
    """The JSON array of the last ``instruction [..]`` (continuation lines joined)."""
    text = DOCKERFILE.replace("\\\n", " ")
    (match,) = re.findall(rf"^{instruction}\b.*?(\[.*\])\s*$", text, flags=re.MULTILINE)[-1:]
    return list(json.loads(match))


def test_the_image_is_slim_non_root_with_a_data_volume() -> None:
    assert re.search(r"^FROM python:3\.11-slim$", DOCKERFILE, flags=re.MULTILINE)
    assert re.search(r"^USER (?!root)\S+$", DOCKERFILE, flags=re.MULTILINE)
    assert 'VOLUME ["/data"]' in DOCKERFILE and "FUZZYRISK_DATA_DIR=/data" in DOCKERFILE
    assert "EXPOSE 8000" in DOCKERFILE and "NUMBA_CACHE_DIR=" in DOCKERFILE and "pip install ." in DOCKERFILE
    assert "curl" not in DOCKERFILE.split("HEALTHCHECK", 1)[1]
    assert _exec_form("CMD") == ["python", "-m", "app", "--host", "0.0.0.0"]


def test_the_healthcheck_command_passes_against_a_running_server_and_fails_without(start_server: Any) -> None:
    command = _exec_form("HEALTHCHECK.*CMD")
    assert command[0] == "python"
    server = start_server()
    env = {**os.environ, "FUZZYRISK_PORT": str(server.port)}
    assert subprocess.run([sys.executable, *command[1:]], env=env, timeout=30).returncode == 0
    server.stop()
    failed = subprocess.run([sys.executable, *command[1:]], env=env, timeout=30, capture_output=True)
    assert failed.returncode != 0
