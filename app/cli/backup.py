"""``python -m app.backup DEST``: a consistent copy of the map database, while the service runs.

The command line of ``app.storage.backup`` (SQLite's online backup, payload files put in their rows):
the copy is a self-contained database, to serve from a ``FUZZYRISK_DATA_DIR`` of its own. Progress
goes to stderr (``app.cli.progress``); Ctrl-C stops it with exit 130 and nothing at the destination.
"""

from __future__ import annotations

import argparse
import sqlite3
import sys
from pathlib import Path

from app.cli.progress import Progress
from app.config import Settings
from app.ops.version import add_version_option
from app.storage.backup import DATABASE, BackupDamaged, backup

PROG = "fuzzyrisk-backup"
#: How a stage of the backup is shown: the storage's name of its work -> (what is being done, its unit).
_STAGES = {"pages": ("copying the database", "pages"), "payload files": ("putting payload files into the copy", "files")}


class _Shown:
    """The backup's progress callback: each stage of ``app.storage.backup`` said, then shown by ``Progress``."""

    def __init__(self, progress: Progress, source: Path, dest: Path) -> None:
        self.progress, self.source, self.dest, self.current = progress, source, dest, ""

    def __call__(self, what: str, done: int, total: int) -> None:
        if what != self.current:
            self.current = what
            self.progress.close()  # the stage before ends with its last figures
            if total == 0:  # a store without payload files: nothing to show
                return
            doing, unit = _STAGES[what]
            self.progress.say(f"{doing}: {total:,} {unit}" + (f" of {self.source} to {self.dest}" if what == "pages"
                                                               else ""))
            self.progress.stage(doing, total, unit)
        self.progress.update(done)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Copy the map database (SQLite) to DEST while the service runs: every "
        "acknowledged batch, never a half-written one, with the payload files put into the copy, so that the "
        "copy is one self-contained file.",
        epilog="To restore, put the copy in an empty data directory as fuzzyrisk.sqlite3 and start the service "
        "on it. Exit status: 0 copied, 1 failed (with a message), 2 bad options, 130 interrupted (Ctrl-C; "
        "nothing is left at DEST).")
    p.add_argument("dest", type=Path, help="the copy to write (must not exist)")
    p.add_argument("--data-dir", type=Path, help="the service's data directory (default FUZZYRISK_DATA_DIR)")
    add_version_option(p)
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the command; the exit code (0 copied, 1 failed with a message, 2 bad options, 130 interrupted)."""
    args = _parser().parse_args(argv)
    data_dir = args.data_dir or Settings().data_dir
    try:
        with Progress(PROG) as progress:
            pages = backup(data_dir, args.dest, _Shown(progress, data_dir / DATABASE, args.dest))
    except (OSError, sqlite3.Error, BackupDamaged) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing was written to {args.dest}", file=sys.stderr)
        return 130
    print(f"{args.dest}: {pages} pages copied from {data_dir / DATABASE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
