"""``python -m app.backup DEST``: a consistent copy of the map database, while the service runs.

SQLite's online backup (``sqlite3.Connection.backup``) copies the database page by page as one
read transaction: it sees every committed batch, including those still in the write-ahead log
that copying ``fuzzyrisk.sqlite3`` alone would miss, and never a half-written one. The service
keeps committing meanwhile. The copy is a self-contained database: point ``FUZZYRISK_DATA_DIR``
at a directory holding it as ``fuzzyrisk.sqlite3`` to serve it.
"""

from __future__ import annotations

import argparse
import sqlite3
import sys
from pathlib import Path

from app.config import Settings

DATABASE = "fuzzyrisk.sqlite3"


def backup(data_dir: Path, dest: Path) -> int:
    """Copy ``data_dir``'s database to ``dest`` (refusing to overwrite); returns the pages copied."""
    source_path = data_dir / DATABASE
    if not source_path.is_file():
        raise FileNotFoundError(f"no map database at {source_path} (FUZZYRISK_DATA_DIR or --data-dir)")
    if dest.exists():
        raise FileExistsError(f"{dest} exists; the backup does not overwrite a file")
    # read-only: the backup never writes the service's database
    source = sqlite3.connect(f"file:{source_path}?mode=ro", uri=True)
    target = sqlite3.connect(dest)
    try:
        source.backup(target)
        return int(target.execute("PRAGMA page_count").fetchone()[0])
    finally:
        target.close()
        source.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="fuzzyrisk-backup", description=__doc__.split("\n\n")[0])
    ap.add_argument("dest", type=Path, help="the copy to write (must not exist)")
    ap.add_argument("--data-dir", type=Path, help="the service's data directory (default FUZZYRISK_DATA_DIR)")
    args = ap.parse_args(argv)
    data_dir = args.data_dir or Settings().data_dir
    try:
        pages = backup(data_dir, args.dest)
    except (OSError, sqlite3.Error) as exc:
        print(f"fuzzyrisk-backup: error: {exc}", file=sys.stderr)
        return 1
    print(f"{args.dest}: {pages} pages copied from {data_dir / DATABASE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
