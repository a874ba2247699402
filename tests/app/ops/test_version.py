"""Every command says its version: ``--version`` prints the installed package's, as pyproject.toml gives it.

The commands are run as a user runs them, each in its own process: the ``python -m`` forms and the
console scripts pyproject.toml installs (each of them, as listed there).
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from collections.abc import Callable
from pathlib import Path

import pytest

from app.config import Settings
from tests.conftest import ROOT

PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
MODULES = ["app", "app.import_log", "app.import_bag", "app.backup", "fuzzyrisk_bridge", "fuzzyocc.figures"]


def _version_of(command: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*command, "--version"], check=False, cwd=ROOT, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("module", MODULES)
def test_each_python_m_command_prints_the_package_version(module: str) -> None:
    result = _version_of([sys.executable, "-m", module])
    assert result.returncode == 0, result.stderr
    assert result.stdout.endswith(f" (fuzzyrisk) {PROJECT['version']}\n") and result.stderr == ""


@pytest.mark.parametrize("script", sorted(PROJECT["scripts"]))
def test_each_console_script_prints_the_package_version(script: str) -> None:
    installed = Path(sys.executable).parent / script  # pip puts the scripts beside the environment's python
    assert installed.is_file(), f"{script} is not installed beside {sys.executable}: pip install -e ."
    result = _version_of([str(installed)])
    assert result.returncode == 0, result.stderr
    assert result.stdout.endswith(f" (fuzzyrisk) {PROJECT['version']}\n")


def test_the_openapi_document_carries_the_package_version(make_settings: Callable[..., Settings]) -> None:
    from app.api.factory import create_app

    assert create_app(make_settings()).openapi()["info"]["version"] == PROJECT["version"]
