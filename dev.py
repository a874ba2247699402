#!/usr/bin/env python3
"""Set up and run the project with nothing but Python 3.11 on the machine.

    python3 dev.py serve [--host H --port P --data-dir D]   # install, then serve
    python3 dev.py test [pytest args]                        # install, then run the tests
    python3 dev.py bench NAME [args]                         # install, then run bench/bench_NAME.py

Each command creates ``.venv`` beside this file when it is missing and installs
the project into it (again only when ``pyproject.toml`` changed), then runs.
The Dockerfile performs the same steps: ``pip install .`` then ``python -m app``.
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


def _ensure_env(extras: str) -> None:
    if sys.version_info < (3, 11):
        sys.exit(f"Python 3.11 or newer is needed, this is {sys.version.split()[0]}")
    if not PYTHON.exists():
        print(f"creating virtual environment in {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    digest = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    stamp = VENV / f".fuzzyrisk-installed-{extras.replace(',', '-') or 'runtime'}"
    if stamp.exists() and stamp.read_text() == digest:
        return
    print(f"installing the project ({extras or 'runtime'} dependencies) into {VENV}", flush=True)
    target = f"{ROOT}[{extras}]" if extras else str(ROOT)
    subprocess.run([str(PYTHON), "-m", "pip", "install", "--quiet", "--upgrade", "pip"], check=True)
    subprocess.run([str(PYTHON), "-m", "pip", "install", "--quiet", "-e", target], check=True)
    stamp.write_text(digest)


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in {"serve", "test", "bench"}:
        print(__doc__, file=sys.stderr)
        return 2
    command, rest = argv[0], argv[1:]
    if command == "serve":
        _ensure_env("")
        return subprocess.call([str(PYTHON), "-m", "app", *rest], cwd=ROOT)
    if command == "bench":
        names = sorted(p.stem.removeprefix("bench_") for p in (ROOT / "bench").glob("bench_*.py"))
        names.append("soak")
        if not rest or rest[0] not in names:
            print(f"usage: python3 dev.py bench {{{','.join(names)}}} [args]", file=sys.stderr)
            return 2
        _ensure_env("test,plots,bench")
        module = "bench.soak" if rest[0] == "soak" else f"bench.bench_{rest[0]}"
        return subprocess.call([str(PYTHON), "-m", module, *rest[1:]], cwd=ROOT)
    _ensure_env("test,plots")
    lint = subprocess.call([str(VENV / "bin" / "lint-imports")], cwd=ROOT)
    if lint != 0:
        return lint
    return subprocess.call([str(PYTHON), "-m", "pytest", *rest], cwd=ROOT)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
