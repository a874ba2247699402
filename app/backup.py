"""``python -m app.backup DEST``: a consistent copy of the map database, while the service runs.

SQLite's online backup (``sqlite3.Connection.backup``) copies the database page by page as one
read transaction: it sees every committed batch, including those still in the write-ahead log
that copying ``fuzzyrisk.sqlite3`` alone would miss, and never a half-written one. The service
keeps committing meanwhile. Rows whose payload is a file beside the database (``app.payloadfiles``)
get that file's bytes in the copy, so the copy is a self-contained database: point
``FUZZYRISK_DATA_DIR`` at a directory holding it as ``fuzzyrisk.sqlite3`` to serve it.
"""

from __future__ import annotations

import argparse
import sqlite3
import sys
from pathlib import Path

from app.config import Settings
from app.payloadfiles import PayloadFiles
from app.storage import payload_directory

DATABASE = "fuzzyrisk.sqlite3"
#: Copies made again when a payload file named in the copy was removed before it was read (its rows
#: went meanwhile: a snapshot covered them, or the map was deleted); a newer copy no longer names it.
ATTEMPTS = 5


def backup(data_dir: Path, dest: Path) -> int:
    """Copy ``data_dir``'s database to ``dest`` (refusing to overwrite); returns the pages copied."""
    source_path = data_dir / DATABASE
    if not source_path.is_file():
        raise FileNotFoundError(f"no map database at {source_path} (FUZZYRISK_DATA_DIR or --data-dir)")
    if dest.exists():
        raise FileExistsError(f"{dest} exists; the backup does not overwrite a file")
    files = PayloadFiles(payload_directory(source_path))
    for attempt in range(1, ATTEMPTS + 1):
        _copy(source_path, dest)
        missing = _inline_payloads(dest, files)
        if not missing or attempt == ATTEMPTS:
            break
        dest.unlink()
    for table, key, file in missing:  # removed behind the service's back: the copy is as damaged as the store
        print(f"fuzzyrisk-backup: warning: {table} row {key} names payload file {file}, which is not in "
              f"{files.directory}; the copy keeps the row as it is (that map will be quarantined)", file=sys.stderr)
    target = sqlite3.connect(dest)
    try:
        return int(target.execute("PRAGMA page_count").fetchone()[0])
    finally:
        target.close()


def _copy(source_path: Path, dest: Path) -> None:
    # read-only: the backup never writes the service's database
    source = sqlite3.connect(f"file:{source_path}?mode=ro", uri=True)
    target = sqlite3.connect(dest)
    try:
        source.backup(target)
    finally:
        target.close()
        source.close()


def _inline_payloads(dest: Path, files: PayloadFiles) -> list[tuple[str, str, str]]:
    """Put the bytes of every payload file the copy names into its row; the (table, row, file) not found."""
    target = sqlite3.connect(dest, isolation_level=None)
    missing = []
    try:
        target.execute("BEGIN")
        for table, key in (("batches", "seq"), ("snapshots", "version")):
            columns = {row[1] for row in target.execute(f"PRAGMA table_info({table})")}
            if "file" not in columns:
                continue  # a database from before payload files
            rows = target.execute(f"SELECT map, {key}, file FROM {table} WHERE file IS NOT NULL").fetchall()
            for name, number, file in rows:
                payload = files.read(file)
                if payload is None:
                    missing.append((table, f"{name!r} {number}", file))
                    continue
                target.execute(f"UPDATE {table} SET payload = ?, file = NULL WHERE map = ? AND {key} = ?",
                               (payload, name, number))
        target.execute("COMMIT")
    finally:
        target.close()
    return missing


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
