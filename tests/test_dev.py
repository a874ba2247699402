"""``python3 dev.py test``, the README's second command: the Debian packages the tests start, installed first
(``dev.ensure_test_packages``), or one line saying what to run where that cannot be done.

The machine that runs these has the packages (the command installed them before pytest); the cases without
them are made with a PATH and a file-system root of the test's own, never by uninstalling anything.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import dev
from tests.conftest import ROOT

EVERY_PACKAGE = "nginx chromium postgresql"


def _path_of(tmp_path: Path, *programs: str) -> str:
    """A PATH of one directory holding links to ``programs`` (paths, or names on this machine's PATH), nothing else."""
    bindir = tmp_path / "bin"
    bindir.mkdir(exist_ok=True)
    for program in programs:
        found = shutil.which(program)
        assert found is not None, f"{program} is not on this machine"
        (bindir / Path(program).name).symlink_to(found)
    return str(bindir)


def _overrides() -> dict[str, str]:
    """The lookups' overrides this run was given (the tests honour them too)."""
    return {name: os.environ[name] for name in ("CHROME", "FUZZYRISK_TEST_PG_BINDIR") if name in os.environ}


def test_with_the_packages_installed_it_finds_all_three_and_installs_nothing(tmp_path: Path) -> None:
    chromium, nginx, bindir = dev.find_chromium(), dev.find_nginx(), dev.find_pg_bindir()
    assert chromium and nginx and bindir, (chromium, nginx, bindir)
    for program in (chromium, nginx, bindir / "initdb", bindir / "postgres"):
        assert os.access(program, os.X_OK), program
    assert dev.missing_test_packages() == []
    # the same programs on a PATH without apt-get or sudo: an attempt to install anything would stop the command
    programs = [chromium, nginx] + ([initdb] if (initdb := shutil.which("initdb")) else [])
    dev.ensure_test_packages({**_overrides(), "PATH": _path_of(tmp_path, *programs)})


def test_as_root_it_installs_only_what_is_missing_with_apt_get_and_no_questions(tmp_path: Path) -> None:
    env = {"PATH": _path_of(tmp_path, "apt-get")}
    assert dev.missing_test_packages(env, root=tmp_path) == EVERY_PACKAGE.split()
    apt = ["env", "DEBIAN_FRONTEND=noninteractive", "apt-get"]
    plan = dev.install_steps(["chromium"], env, euid=0)
    assert plan == [[*apt, "update", "-qq"], [*apt, "install", "-y", "-qq", "chromium"]]


def test_without_apt_get_it_stops_at_once_with_one_line_naming_the_command(tmp_path: Path) -> None:
    nothing = {"PATH": _path_of(tmp_path)}
    with pytest.raises(SystemExit) as stopped:
        dev.ensure_test_packages(nothing, root=tmp_path, euid=0)
    line = str(stopped.value.code)
    assert "\n" not in line and stopped.value.code != 0
    assert "no apt-get" in line and line.endswith(f"run `apt-get install -y {EVERY_PACKAGE}`"), line


def test_not_root_and_without_sudo_it_names_the_sudo_command(tmp_path: Path) -> None:
    env = {"PATH": _path_of(tmp_path, "apt-get")}  # apt-get, but nothing to become root with
    with pytest.raises(dev.CannotInstall, match="not root and there is no sudo"):
        dev.install_steps(["nginx"], env, euid=1000)
    with pytest.raises(SystemExit) as stopped:
        dev.ensure_test_packages(env, root=tmp_path, euid=1000)
    line = str(stopped.value.code)
    assert "\n" not in line and line.endswith(f"run `sudo apt-get install -y {EVERY_PACKAGE}`"), line


def test_a_failing_step_stops_with_the_command_and_its_last_error_line() -> None:
    apt_said = ("import sys; print('Reading package lists...', file=sys.stderr); "
                "sys.exit('E: Unable to locate package chromium')")
    failing = [sys.executable, "-c", apt_said]
    with pytest.raises(dev.CannotInstall) as failed:
        dev.run_steps([[sys.executable, "-c", "pass"], failing], os.environ)
    assert str(failed.value).endswith("failed: E: Unable to locate package chromium")
    assert "\n" not in str(failed.value)


@pytest.mark.parametrize(("override", "said"), [
    ("CHROME", "CHROME={} is not an executable"),
    ("FUZZYRISK_TEST_PG_BINDIR", "FUZZYRISK_TEST_PG_BINDIR={} does not hold initdb and postgres"),
])
def test_the_command_stops_before_any_install_when_an_override_points_at_nothing(
    tmp_path: Path, override: str, said: str,
) -> None:
    """The real command: one line, a non-zero status, and neither a virtual environment made nor pytest run."""
    nowhere, venv = str(tmp_path / "nowhere"), tmp_path / "venv"
    env = {**os.environ, override: nowhere, "FUZZYRISK_VENV": str(venv)}
    done = subprocess.run([sys.executable, "dev.py", "test", "tests/test_health.py"], check=False, cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    assert done.stderr.splitlines() == [done.stderr.strip()] and said.format(nowhere) in done.stderr, done.stderr
    assert done.stdout == "" and not venv.exists()
