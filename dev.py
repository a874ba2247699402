#!/usr/bin/env python3
"""Set up and run the project with nothing but Python 3.11 on the machine.

    python3 dev.py serve [--host H --port P --data-dir D]   # install, then serve
    python3 dev.py test [pytest args]                        # install, then run the tests
    python3 dev.py bench NAME [args]                         # install, then run bench/bench_NAME.py

Each command creates ``.venv`` beside this file when it is missing and installs
the project into it with the pinned versions of ``constraints.txt`` (again only when
``pyproject.toml`` or ``constraints.txt`` changed), then runs. ``test`` first installs the
Debian packages whose programs the tests start (``TEST_PACKAGES``) when they are missing, with
``apt-get`` (through ``sudo`` when not root); where that cannot be done, it stops at once with
one line naming the command to run. The last step replaces this process (``exec``), so a
signal sent to ``python3 dev.py serve`` (SIGTERM, Ctrl-C) reaches the server itself. The
Dockerfile performs the same steps: ``pip install -c constraints.txt .`` then ``python -m app``.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import venv
from collections.abc import Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = Path(os.environ.get("FUZZYRISK_VENV", ROOT / ".venv"))
PYTHON = VENV / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
CONSTRAINTS = "constraints.txt"
#: Debian packages whose programs the tests start: nginx (the fleet's load balancer), Chromium (the
#: browser tests), PostgreSQL's server (a throwaway cluster for the store's and the fleet's tests).
TEST_PACKAGES = ("nginx", "chromium", "postgresql")


def find_chromium(env: Mapping[str, str] = os.environ) -> str | None:
    """The Chromium the browser tests drive: ``$CHROME``, else ``chromium`` or ``chromium-browser`` on the PATH."""
    path = env.get("PATH", os.defpath)
    if env.get("CHROME"):
        return shutil.which(env["CHROME"], path=path)
    return shutil.which("chromium", path=path) or shutil.which("chromium-browser", path=path)


def find_nginx(env: Mapping[str, str] = os.environ, root: Path = Path("/")) -> str | None:
    """nginx on the PATH, else Debian's ``/usr/sbin/nginx`` (sbin is not on every user's PATH)."""
    sbin = root / "usr" / "sbin" / "nginx"
    return shutil.which("nginx", path=env.get("PATH", os.defpath)) or (str(sbin) if os.access(sbin, os.X_OK) else None)


def pg_bindir_candidates(env: Mapping[str, str] = os.environ, root: Path = Path("/")) -> list[Path]:
    """Where PostgreSQL's ``initdb`` and ``postgres`` are looked for, in order: ``$FUZZYRISK_TEST_PG_BINDIR`` alone
    when set; else Debian's ``/usr/lib/postgresql/*/bin``, newest first, then the directory of the PATH's initdb."""
    if env.get("FUZZYRISK_TEST_PG_BINDIR"):
        return [Path(env["FUZZYRISK_TEST_PG_BINDIR"])]

    def major(bindir: Path) -> tuple[int, ...]:
        return tuple(int(part) for part in bindir.parent.name.split(".") if part.isdigit())

    candidates = sorted((root / "usr" / "lib" / "postgresql").glob("*/bin"), key=major, reverse=True)
    initdb = shutil.which("initdb", path=env.get("PATH", os.defpath))
    return candidates + ([Path(initdb).resolve().parent] if initdb else [])


def find_pg_bindir(env: Mapping[str, str] = os.environ, root: Path = Path("/")) -> Path | None:
    """The first of ``pg_bindir_candidates`` holding both ``initdb`` and ``postgres``."""
    for bindir in pg_bindir_candidates(env, root):
        if all(os.access(bindir / name, os.X_OK) for name in ("initdb", "postgres")):
            return bindir
    return None


def missing_test_packages(env: Mapping[str, str] = os.environ, root: Path = Path("/")) -> list[str]:
    """The packages of ``TEST_PACKAGES`` whose program is not found, in that order."""
    found = {"nginx": find_nginx(env, root), "chromium": find_chromium(env), "postgresql": find_pg_bindir(env, root)}
    return [package for package in TEST_PACKAGES if found[package] is None]


class CannotInstall(Exception):
    """Why the missing packages cannot be installed from here."""


def install_steps(packages: list[str], env: Mapping[str, str], euid: int) -> list[list[str]]:
    """The commands that install ``packages``: apt-get as root, else through ``sudo -n`` (never a password prompt:
    this may run unattended); ``CannotInstall`` when neither can run here."""
    path = env.get("PATH", os.defpath)
    if shutil.which("apt-get", path=path) is None:
        raise CannotInstall("there is no apt-get on the PATH")
    as_root: list[str] = []
    if euid != 0:
        sudo = shutil.which("sudo", path=path)
        if sudo is None:
            raise CannotInstall("this is not root and there is no sudo on the PATH")
        asked = subprocess.run([sudo, "-n", "true"], check=False, stdin=subprocess.DEVNULL, capture_output=True)
        if asked.returncode != 0:
            raise CannotInstall("this is not root and sudo asks for a password")
        as_root = ["sudo", "-n"]
    apt = [*as_root, "env", "DEBIAN_FRONTEND=noninteractive", "apt-get"]  # no questions: no one may be there to answer
    return [[*apt, "update", "-qq"], [*apt, "install", "-y", "-qq", *packages]]


def run_steps(steps: list[list[str]], env: Mapping[str, str]) -> None:
    """Run each command, quietly; ``CannotInstall`` with the command and its last error line when one fails."""
    for step in steps:
        done = subprocess.run(step, check=False, env=dict(env), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
        if done.returncode != 0:
            said = done.stderr.strip().splitlines() or [f"exit status {done.returncode}"]
            raise CannotInstall(f"`{' '.join(step)}` failed: {said[-1].strip()}")


def ensure_test_packages(env: Mapping[str, str] = os.environ, root: Path = Path("/"), euid: int | None = None) -> None:
    """Install the packages of ``TEST_PACKAGES`` whose programs are missing; when that cannot be done, exit at
    once (status 1) with one line naming the command to run. A ``$CHROME`` or ``$FUZZYRISK_TEST_PG_BINDIR``
    that points at nothing is the user's to fix: no package would change what the tests run then."""
    if env.get("CHROME") and find_chromium(env) is None:
        sys.exit(f"CHROME={env['CHROME']} is not an executable on the PATH: point it at Chromium, or unset it")
    if env.get("FUZZYRISK_TEST_PG_BINDIR") and find_pg_bindir(env, root) is None:
        sys.exit(f"FUZZYRISK_TEST_PG_BINDIR={env['FUZZYRISK_TEST_PG_BINDIR']} does not hold initdb and postgres: "
                 "point it at PostgreSQL's bin directory, or unset it")
    missing = missing_test_packages(env, root)
    if not missing:
        return
    if euid is None:
        euid = os.geteuid() if hasattr(os, "geteuid") else 1  # Windows: no root, no apt-get
    command = f"{'sudo ' if euid != 0 else ''}apt-get install -y {' '.join(missing)}"
    try:
        steps = install_steps(missing, env, euid)
        print(f"installing {', '.join(missing)} (Debian packages the tests start) with apt-get", flush=True)
        run_steps(steps, env)
    except CannotInstall as why:
        sys.exit(f"the tests need {', '.join(missing)} (Debian packages), and {why}: run `{command}`")
    if still := missing_test_packages(env, root):
        sys.exit(f"apt-get installed {', '.join(missing)}, yet {', '.join(still)} is still not found: run `{command}`")


def _ensure_env(extras: str) -> None:
    if sys.version_info < (3, 11):
        sys.exit(f"Python 3.11 or newer is needed, this is {sys.version.split()[0]}")
    if not PYTHON.exists():
        print(f"creating virtual environment in {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    digest = hashlib.sha256((ROOT / "pyproject.toml").read_bytes() + (ROOT / CONSTRAINTS).read_bytes()).hexdigest()
    stamp = VENV / f".fuzzyrisk-installed-{extras.replace(',', '-') or 'runtime'}"
    wanted = set(filter(None, extras.split(",")))
    for done in VENV.glob(".fuzzyrisk-installed-*"):  # an install with more extras covers this one
        installed = set(done.name.removeprefix(".fuzzyrisk-installed-").split("-")) - {"runtime"}
        if wanted <= installed and done.read_text() == digest:
            return
    print(f"installing the project ({extras or 'runtime'} dependencies) into {VENV}", flush=True)
    target = f"{ROOT}[{extras}]" if extras else str(ROOT)
    pip = [str(PYTHON), "-m", "pip", "install", "--quiet", "--constraint", str(ROOT / CONSTRAINTS)]
    subprocess.run([*pip, "--upgrade", "pip"], check=True)
    subprocess.run([*pip, "-e", target], check=True)
    stamp.write_text(digest)


def _become(args: list[str]) -> int:
    """Run ``args`` in ROOT in place of this process (signals then reach it directly); a child where there is no exec."""
    sys.stdout.flush()
    sys.stderr.flush()
    if os.name == "nt":
        return subprocess.call(args, cwd=ROOT)
    os.chdir(ROOT)
    os.execv(args[0], args)


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in {"serve", "test", "bench"}:
        print(__doc__, file=sys.stderr)
        return 2
    command, rest = argv[0], argv[1:]
    if command == "serve":
        _ensure_env("")
        return _become([str(PYTHON), "-m", "app", *rest])
    if command == "bench":
        names = sorted(p.stem.removeprefix("bench_") for p in (ROOT / "bench").glob("bench_*.py"))
        names.append("soak")
        if not rest or rest[0] not in names:
            print(f"usage: python3 dev.py bench {{{','.join(names)}}} [args]", file=sys.stderr)
            return 2
        _ensure_env("test,plots,bench")
        # the servers a benchmark starts, each on a new data directory, share one kernel cache (as the tests do)
        os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))
        module = "bench.soak" if rest[0] == "soak" else f"bench.bench_{rest[0]}"
        return _become([str(PYTHON), "-m", module, *rest[1:]])
    ensure_test_packages()  # first: a machine that cannot have them stops before minutes of pip
    _ensure_env("test,plots")
    lint = subprocess.call([str(VENV / "bin" / "lint-imports")], cwd=ROOT)
    if lint != 0:
        return lint
    return _become([str(PYTHON), "-m", "pytest", *rest])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
