#!/usr/bin/env python3
"""Set up and run the project with nothing but Python 3.11 on the machine.

    python3 dev.py serve [--host H --port P --data-dir D]   # install, then serve
    python3 dev.py test [pytest args]                        # install, then run the tests
    python3 dev.py bench NAME [args]                         # install, then run bench/bench_NAME.py

Each command creates ``.venv`` beside this file when it is missing and installs
the project into it with the pinned versions of ``constraints.txt`` (again only when
``pyproject.toml`` or ``constraints.txt`` changed), then runs. The last step replaces
this process (``exec``), so a signal sent to ``python3 dev.py serve`` (SIGTERM, Ctrl-C)
reaches the server itself. The Dockerfile performs the same steps: ``pip install -c
constraints.txt .`` then ``python -m app``.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = Path(os.environ.get("FUZZYRISK_VENV", ROOT / ".venv"))
PYTHON = VENV / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
CONSTRAINTS = "constraints.txt"


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
    _ensure_env("test,plots")
    lint = subprocess.call([str(VENV / "bin" / "lint-imports")], cwd=ROOT)
    if lint != 0:
        return lint
    return _become([str(PYTHON), "-m", "pytest", *rest])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
