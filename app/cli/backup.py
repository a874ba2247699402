"""``python -m app.backup DEST``: a consistent copy of the map database, while the service runs.

The command line of ``app.storage.backup`` (SQLite's online backup, payload files put in their rows):
the copy is a self-contained database, to serve from a ``FUZZYRISK_DATA_DIR`` of its own.
"""

from __future__ import annotations

import argparse
import sqlite3
import sys
from pathlib import Path

from app.config import Settings
from app.storage.backup import DATABASE, BackupDamaged, backup


def main(argv: list[str] | None = None) -> int:
    """Run the command; the exit code (0 copied, 1 failed with a message, 2 bad options)."""
    ap = argparse.ArgumentParser(prog="fuzzyrisk-backup", description=__doc__.split("\n\n")[0])
    ap.add_argument("dest", type=Path, help="the copy to write (must not exist)")
    ap.add_argument("--data-dir", type=Path, help="the service's data directory (default FUZZYRISK_DATA_DIR)")
    args = ap.parse_args(argv)
    data_dir = args.data_dir or Settings().data_dir
    try:
        pages = backup(data_dir, args.dest)
    except (OSError, sqlite3.Error, BackupDamaged) as exc:
        print(f"fuzzyrisk-backup: error: {exc}", file=sys.stderr)
        return 1
    print(f"{args.dest}: {pages} pages copied from {data_dir / DATABASE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
