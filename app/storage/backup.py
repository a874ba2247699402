"""A consistent copy of the SQLite map database, with its payload files, while the service runs.

SQLite's online backup (``sqlite3.Connection.backup``) copies the database page by page as one
read transaction: it sees every committed batch, including those still in the write-ahead log
that copying ``fuzzyrisk.sqlite3`` alone would miss, and never a half-written one. The service
keeps committing meanwhile. Rows whose payload is a file beside the database (``app.storage.payloadfiles``)
get that file's bytes in the copy, so the copy is a self-contained database: point
``FUZZYRISK_DATA_DIR`` at a directory holding it as ``fuzzyrisk.sqlite3`` to serve it.

The pages are copied ``PAGES_PER_STEP`` at a time, each step reported to a ``progress`` callback
(SQLite's backup progress): a caller shows it, and a Ctrl-C stops the copy at the next step.

``python -m app.backup`` (``app.cli.backup``) is its command line.
"""

from __future__ import annotations

import errno
import resource
import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from app.storage.payloadfiles import PayloadFiles, PayloadUnreadable
from app.storage.sqlite import payload_directory

#: The database's file in the data directory (as ``Settings.database_path`` names it).
DATABASE = "fuzzyrisk.sqlite3"
_TABLES = (("batches", "seq"), ("snapshots", "version"), ("bases", "version"))
#: Pages copied between two progress reports: 4 MiB of the default 4 KiB pages, a few milliseconds of copying.
PAGES_PER_STEP = 1024

#: Told of the work done so far: ``(what, done, total)``, what being ``pages`` (of the database), then
#: ``payload files`` (put into the copy's rows).
BackupProgress = Callable[[str, int, int], None]


def _quiet(what: str, done: int, total: int) -> None:
    pass


class BackupDamaged(Exception):
    """The store names payload files it does not have: the maps they belong to are damaged (quarantined)."""


def backup(data_dir: Path, dest: Path, progress: BackupProgress = _quiet) -> int:
    """Copy ``data_dir``'s database to ``dest`` (refusing to overwrite), telling ``progress``; returns the pages
    copied.

    Written as ``<dest>.partial`` and renamed when complete: a backup that fails or is interrupted
    (an exception, ``KeyboardInterrupt`` included, raised by ``progress`` or anywhere in the copy)
    removes it, and leaves nothing at ``dest``.
    """
    source_path = data_dir / DATABASE
    if not source_path.is_file():
        raise FileNotFoundError(f"no map database at {source_path} (FUZZYRISK_DATA_DIR or --data-dir)")
    if dest.exists():
        raise FileExistsError(f"{dest} exists; the backup does not overwrite a file")
    partial = dest.with_name(dest.name + ".partial")
    partial.unlink(missing_ok=True)  # left by a backup that was interrupted
    try:
        _copy(source_path, partial, PayloadFiles(payload_directory(source_path)), progress)
        target = sqlite3.connect(partial)
        try:
            pages = int(target.execute("PRAGMA page_count").fetchone()[0])
        finally:
            target.close()
        partial.rename(dest)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return pages


#: Read transactions tried before missing payload files count as damage: a snapshot that commits between the
#: transaction's first read and the opening of its files removes files that the transaction's rows still name.
SNAPSHOT_TRIES = 5


def _copy(source_path: Path, target_path: Path, files: PayloadFiles, progress: BackupProgress) -> None:
    """The database as of one read transaction, with the payload files its rows name put into those rows.

    The files are opened inside that transaction, before the pages are copied: a snapshot or a delete
    that removes them afterwards cannot take them from the copy (an open file stays readable). One that
    removed them before they were opened (its rows are gone from a newer transaction) makes the backup
    start again in a new transaction; files still missing there are damage.
    """
    # read-only: the backup never writes the service's database
    source = sqlite3.connect(f"file:{source_path}?mode=ro", uri=True, isolation_level=None)
    target = sqlite3.connect(target_path, isolation_level=None)
    opened: dict[str, BinaryIO] = {}
    try:
        for attempt in range(1, SNAPSHOT_TRIES + 1):
            source.execute("BEGIN")
            named, missing = _open_named(source, files, opened)
            if not missing:
                break
            source.execute("ROLLBACK")
            _close(opened)
            if attempt == SNAPSHOT_TRIES:
                raise BackupDamaged("the store's rows name payload files that cannot be read, so its maps "
                                    f"{sorted(missing)} are damaged (quarantined by the service); drop them "
                                    "(DELETE /maps/NAME) or restore an earlier backup: " + "; ".join(missing.values()))
        _copy_pages(source, target, progress)
        source.execute("COMMIT")
        target.execute("PRAGMA journal_mode=DELETE")  # the copy is one file; and its log is not a second copy
        target.execute("BEGIN")
        total, done = sum(len(rows) for rows in named.values()), 0
        progress("payload files", done, total)
        for (table, key), rows in named.items():
            for name, number, file in rows:
                target.execute(f"UPDATE {table} SET payload = ?, file = NULL WHERE map = ? AND {key} = ?",
                               (opened[file].read(), name, number))
                done += 1
                progress("payload files", done, total)
        target.execute("COMMIT")
    finally:
        _close(opened)
        target.close()
        source.close()


def _close(opened: dict[str, BinaryIO]) -> None:
    for file in opened.values():
        file.close()
    opened.clear()


def _open_named(source: sqlite3.Connection, files: PayloadFiles, opened: dict[str, BinaryIO]
                ) -> tuple[dict[tuple[str, str], list[tuple[str, int, str]]], dict[str, str]]:
    """Open every payload file the source's rows name, in its read transaction: the rows, by table, and the
    maps whose files could not be opened (with why)."""
    named: dict[tuple[str, str], list[tuple[str, int, str]]] = {}
    missing: dict[str, str] = {}
    for table, key in _TABLES:
        if "file" not in {row[1] for row in source.execute(f"PRAGMA table_info({table})")}:
            continue  # a database from before payload files
        named[(table, key)] = source.execute(f"SELECT map, {key}, file FROM {table} WHERE file IS NOT NULL").fetchall()
    _allow_open_files(sum(len(rows) for rows in named.values()))
    for rows in named.values():
        for name, _, file in rows:
            try:
                opened[file] = files.open(file)
            except PayloadUnreadable as exc:
                missing[name] = str(exc)
    return named, missing


def _allow_open_files(count: int) -> None:
    """Raise this process's limit of open files to hold ``count`` more (up to the hard limit), or say why not.

    Every payload file stays open until its bytes are in the copy: a store may hold many thousands
    (up to ``FUZZYRISK_MAX_HISTORY_BYTES`` / 256 KiB a map), beyond a shell's usual 1,024.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    needed = count + 64  # the databases, the standard streams and some room
    if needed <= soft:
        return
    if hard != resource.RLIM_INFINITY and needed > hard:
        raise OSError(errno.EMFILE, f"the store has {count} payload files, which the backup holds open at once, "
                      f"beyond this process's hard limit of {hard} open files: raise it (ulimit -Hn) and run again")
    resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))


def _copy_pages(source: sqlite3.Connection, target: sqlite3.Connection, progress: BackupProgress) -> None:
    # inside the source's read transaction (the rows _open_named listed): its pages cannot change between steps
    progress("pages", 0, int(source.execute("PRAGMA page_count").fetchone()[0]))
    source.backup(target, pages=PAGES_PER_STEP,
                  progress=lambda status, remaining, total: progress("pages", total - remaining, total))
