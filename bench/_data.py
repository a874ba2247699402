"""Where the benchmarks find recorded data: one option, ``--data DIR``, for every bench that reads it.

A data directory holds ``carmen/*.log.gz`` (the recorded CARMEN logs). The default is ``../shared/data``
beside the repository where that folder exists, else the repository's own ``tests/data`` (the nine CARMEN
logs, ``tests/data/README.md``), so that a bare clone runs the benches on the logs it carries.

A bench adds the option with ``add_option(parser)`` and calls ``use(args)`` once its arguments are parsed;
``bench/_logmaps.py`` then reads the logs of ``data_dir()``. A missing file or folder ends the run with a
message naming the directory and the option (``needed``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The maintainers' data, checked out beside the repository (the default where it exists).
SHARED = ROOT.parent / "shared" / "data"
#: The data kept in the repository (the CARMEN logs the tests read).
IN_REPOSITORY = ROOT / "tests" / "data"
OPTION = "--data"

_given: Path | None = None  # set by use() from --data


def default_dir() -> Path:
    """``../shared/data`` beside the repository where it exists, else the repository's ``tests/data``."""
    return SHARED if SHARED.is_dir() else IN_REPOSITORY


def data_dir() -> Path:
    """The data directory of this run: the one ``--data`` gave, else ``default_dir()``."""
    return _given if _given is not None else default_dir()


def add_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    parser.add_argument(OPTION, type=Path, default=None, metavar="DIR",
                        help="data directory holding carmen/*.log.gz (default: ../shared/data beside the "
                             "repository where it exists, else the repository's tests/data; now "
                             f"{_shown(default_dir())})")


def use(args: argparse.Namespace) -> Path:
    """Take ``--data`` from parsed arguments (SystemExit when it is not a directory); the directory in use."""
    global _given
    given: Path | None = getattr(args, "data", None)
    if given is not None:
        if not given.is_dir():
            raise SystemExit(f"{OPTION} {given}: no such directory (give a folder holding carmen/*.log.gz)")
        _given = given.resolve()
    return data_dir()


def needed(relative: str) -> Path:
    """``relative`` (a file or folder) in the data directory; SystemExit naming ``--data`` when it is missing."""
    path = data_dir() / relative
    if not path.exists():
        raise SystemExit(f"{path} is missing: {describe()}; name a data directory with {relative} in it: "
                         f"{OPTION} DIR")
    return path


def describe() -> str:
    """Which data directory is in use and why, for messages."""
    if _given is not None:
        return f"the data directory is {_shown(_given)} ({OPTION})"
    why = "../shared/data beside the repository" if data_dir() == SHARED else \
        "the repository's tests/data, as there is no ../shared/data beside the repository"
    return f"the data directory is {_shown(data_dir())} (default: {why})"


def _shown(path: Path) -> str:
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)
