"""``SqliteStorage``: the ``Storage`` of one process, in one SQLite file beside its big payloads' files."""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from app.storage.base import (
    BATCH_BYTES,
    HISTORY_FROM_STAMP,
    HISTORY_OF_ROWS,
    INLINE_BYTES,
    NO_LIMIT,
    START_ROWS,
    TOMBSTONE,
    BatchRecord,
    CommitUncertain,
    MapGone,
    MapHead,
    NameTaken,
    StorageUnavailable,
    StoredMap,
    checksum,
    fold_point_of,
    fold_rows,
    head_of,
    may_fold,
    read_map,
    start_of,
)
from app.storage import corrections
from app.storage.corrections import StoredCorrection, Switch
from app.storage.payloadfiles import PayloadFiles, Prefetched

T = TypeVar("T")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS maps (
    name TEXT PRIMARY KEY,
    meta TEXT NOT NULL,
    updated TEXT NOT NULL,
    version INTEGER,
    snapshot_version INTEGER,
    incarnation TEXT,
    scans INTEGER NOT NULL DEFAULT 0,
    base_version INTEGER NOT NULL DEFAULT 0,
    history_bytes INTEGER NOT NULL DEFAULT 0,
    history_scans INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS batches (
    map TEXT NOT NULL REFERENCES maps(name) ON DELETE CASCADE,
    seq INTEGER NOT NULL,
    payload BLOB NOT NULL,
    crc INTEGER,
    scans INTEGER,
    updated TEXT,
    file TEXT,
    bytes INTEGER,
    PRIMARY KEY (map, seq)
);
""" + "".join(f"""
CREATE TABLE IF NOT EXISTS {table} (
    map TEXT PRIMARY KEY REFERENCES maps(name) ON DELETE CASCADE,
    version INTEGER NOT NULL,
    payload BLOB NOT NULL,
    crc INTEGER,
    updated TEXT,
    file TEXT
);""" for table in ("snapshots", "bases"))  # a map's restart snapshot and its base snapshot

#: Columns added since the first schema: an old database gets them (NULL, or the default) at open.
_ADDED_COLUMNS = {
    "maps": {"version": "INTEGER", "snapshot_version": "INTEGER", "incarnation": "TEXT",
             "scans": "INTEGER NOT NULL DEFAULT 0", "base_version": "INTEGER NOT NULL DEFAULT 0",
             "history_bytes": "INTEGER NOT NULL DEFAULT 0", "history_scans": "INTEGER NOT NULL DEFAULT 0"},
    "batches": {"crc": "INTEGER", "scans": "INTEGER", "updated": "TEXT", "file": "TEXT", "bytes": "INTEGER",
                "poses": "BLOB", "first_stamp": "INTEGER"},
    "snapshots": {"crc": "INTEGER", "updated": "TEXT", "file": "TEXT"},
}

# A database from before the maps kept their versions has NULL there: its newest is read off its rows.
_SQLITE_NEWEST = ("COALESCE(maps.version, MAX(COALESCE(maps.snapshot_version, 0),"
                  " COALESCE((SELECT MAX(seq) FROM batches WHERE map = maps.name), 0),"
                  " COALESCE((SELECT version FROM snapshots WHERE map = maps.name), 0)))")
_SQLITE_HEAD = ("SELECT name, meta, updated, " + _SQLITE_NEWEST + ", COALESCE(maps.snapshot_version, "
                "(SELECT version FROM snapshots WHERE map = maps.name), 0), scans, incarnation, base_version, history_bytes, "
                "history_scans, " + HISTORY_FROM_STAMP + " FROM maps")

_SQLITE_CREATE = ("INSERT INTO maps (name, meta, updated, version, snapshot_version, incarnation, scans) "
                  "VALUES (?, ?, ?, 0, 0, ?, 0)")


def _store_snapshot(db: sqlite3.Connection, name: str, version: int, payload: bytes, crc: int, file: str | None) -> None:
    """The map's restart snapshot row replaced by ``payload`` at ``version`` (its bytes in ``file`` when staged), with
    that version's batch's ``updated``."""
    db.execute("INSERT INTO snapshots (map, version, payload, crc, updated, file) VALUES (?, ?, ?, ?, "
               "(SELECT updated FROM batches WHERE map = ? AND seq = ?), ?) "
               "ON CONFLICT(map) DO UPDATE SET version = excluded.version, payload = excluded.payload, "
               "crc = excluded.crc, updated = excluded.updated, file = excluded.file",
               (name, version, payload if file is None else b"", crc, name, version, file))
    db.execute("UPDATE maps SET snapshot_version = ? WHERE name = ?", (version, name))


def payload_directory(database: Path) -> Path:
    """Where the SQLite store at ``database`` keeps its big payloads: ``<database>-payloads``, beside its ``-wal``."""
    return database.with_name(database.name + "-payloads")


class SqliteStorage:
    """``Storage`` in one SQLite file: WAL journal, ``synchronous=FULL`` (fsync at every commit).

    One connection shared by the service's threads behind a lock: SQLite has one
    writer at a time anyway, and the commits are short next to fusion. Payloads over
    ``INLINE_BYTES`` are files in ``payload_directory``, written before the lock is
    taken. One process only: replicas share a ``app.storage.postgres.PostgresStorage``.
    """

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._files = PayloadFiles(payload_directory(path))
        # isolation_level=None: transactions are opened explicitly, so each method is one commit
        self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            self._db.executescript(_SCHEMA)
            self._db.execute(corrections.SCHEMA.format(blob="BLOB", int="INTEGER", real="REAL"))
            # an old database: its rows keep NULL there (a crc: not verifiable; a version: not checked until
            # the next write; an incarnation: matched by None), new ones get a value
            counted = "history_bytes" in {row[1] for row in self._db.execute("PRAGMA table_info(maps)")}
            for table, added in _ADDED_COLUMNS.items():
                columns = {row[1] for row in self._db.execute(f"PRAGMA table_info({table})")}
                for column, declaration in added.items():
                    if column not in columns:
                        self._db.execute(f"ALTER TABLE {table} ADD COLUMN {column} {declaration}")
            if not counted:  # a database from before the history: it holds the batches after the snapshot
                self._db.execute(f"UPDATE maps SET (history_bytes, history_scans) = {HISTORY_OF_ROWS}")
            # files of writes that never committed, or whose rows went before them, go (if no other store is open)
            self._files.attach(lambda: {file for (file,) in self._db.execute(
                "SELECT file FROM batches WHERE file IS NOT NULL UNION SELECT file FROM snapshots WHERE file IS NOT NULL "
                "UNION SELECT file FROM bases WHERE file IS NOT NULL")})

    def _stage(self, payload: bytes) -> str | None:
        """A big payload written to its file (outside the lock); None for one that goes in its row."""
        if len(payload) <= INLINE_BYTES:
            return None
        try:
            return self._files.write(payload)
        except OSError as exc:
            raise StorageUnavailable(f"the payload file could not be written in {self._files.directory}: {exc}") from exc

    def _with_files(self, staged: list[str], work: Callable[[sqlite3.Connection], tuple[T, list[str]]]) -> T:
        """``_transaction(work)``, where ``work`` also returns the files its rows no longer name.

        Those are removed once the transaction is on disk; the ``staged`` files, when it fails (but when
        it may have committed, they stay for the next open to sweep, or to serve should the rows be there).
        """
        try:
            result, dropped = self._transaction(work)
        except CommitUncertain:
            raise
        except BaseException:
            self._files.remove(staged)
            raise
        self._files.remove(dropped)
        return result

    def _transaction(self, work: Callable[[sqlite3.Connection], T]) -> T:
        """Run ``work`` in one immediate transaction: all of it is on disk when this returns.

        ``StorageUnavailable`` (nothing written) when SQLite cannot write: a full disk, a
        read-only directory or an I/O error, at any statement or at the COMMIT itself, except
        ``CommitUncertain`` for an I/O error at the COMMIT (its log frames may be written, and a
        recovery after a crash may bring them back). Any other exception of ``work``
        (``MapGone``) rolls back and goes through as it is.
        """
        with self._lock:
            if self._db.in_transaction:  # left open by a ROLLBACK that failed too
                self._rollback()
            committing = False
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    result = work(self._db)
                    # inside the try: a COMMIT that fails (SQLITE_FULL at the WAL append) leaves
                    # the transaction open, and the next BEGIN would fail on it
                    committing = True
                    self._db.execute("COMMIT")
                except BaseException:
                    self._rollback()
                    raise
            except sqlite3.OperationalError as exc:
                code = getattr(exc, "sqlite_errorname", "?")
                # the primary code: a newer SQLite's extended code may have no name in this Python
                if committing and getattr(exc, "sqlite_errorcode", 0) & 0xFF == sqlite3.SQLITE_IOERR:
                    raise CommitUncertain(f"{exc} (SQLite {code}, at the commit)") from exc
                raise StorageUnavailable(f"{exc} (SQLite {code})") from exc
            return result

    def _write(self, statements: list[tuple[str, tuple[Any, ...]]]) -> None:
        def run(db: sqlite3.Connection) -> None:
            for sql, args in statements:
                db.execute(sql, args)

        self._transaction(run)

    def _rollback(self) -> None:
        # SQLite may already have rolled back by itself (some SQLITE_FULL and IOERR cases)
        if self._db.in_transaction:
            try:
                self._db.execute("ROLLBACK")
            except sqlite3.Error:
                pass  # the original error is the one to report

    def map_names(self) -> list[str]:
        with self._lock:
            return [name for (name,) in self._db.execute("SELECT name FROM maps ORDER BY name")]

    def map_head(self, name: str) -> MapHead | None:
        with self._lock:
            row = self._db.execute(_SQLITE_HEAD + " WHERE name = ?", (name,)).fetchone()
        return None if row is None else head_of(row)

    def map_heads(self) -> list[MapHead]:
        with self._lock:
            rows = self._db.execute(_SQLITE_HEAD + " ORDER BY name").fetchall()
        return [head_of(row) for row in rows]

    def load_map(self, name: str) -> StoredMap | None:
        return self._load(name, None, None)

    def load_since(self, name: str, after: int, up_to: int | None = None) -> StoredMap | None:
        return self._load(name, after, up_to)

    def load_history(self, name: str, up_to: int | None = None, after: int | None = None) -> StoredMap | None:
        return self._load(name, after, up_to, from_base=True)

    def _load(self, name: str, after: int | None, up_to: int | None, *, from_base: bool = False) -> StoredMap | None:
        """``read_map`` with the map's payload files read between two holds of the lock, not under it: 256 MiB
        of log read for an MCAP export held every map's commits for as long.

        The files' names are read under the lock, the files after it; the rows are then read in one
        view (a file named by a row committed in between is read then; one removed in between belongs
        to no row any more).
        """
        with self._lock:
            start, table = start_of(*self._db.execute(START_ROWS, (name, name)).fetchone(), from_base=from_base)
            lower = start if after is None else max(after, start)
            names = [file for (file,) in self._db.execute(
                "SELECT file FROM batches WHERE map = ? AND seq > ? AND seq <= ? AND file IS NOT NULL",
                (name, lower, NO_LIMIT if up_to is None else up_to))]
            if table is not None and (after is None or start > after):
                names += [file for (file,) in self._db.execute(
                    f"SELECT file FROM {table} WHERE map = ? AND file IS NOT NULL", (name,))]
        files = Prefetched(self._files, names)
        with self._lock:  # one connection, so no write comes between the queries
            return read_map(self._db.execute, name, after, up_to, files, from_base=from_base)

    def create_map(self, name: str, meta: dict[str, Any], updated: str) -> None:
        try:
            self._write([(_SQLITE_CREATE, (name, json.dumps(meta), updated, meta.get("incarnation")))])
        except sqlite3.IntegrityError:
            raise NameTaken(name) from None

    def delete_map(self, name: str, incarnation: str | None = None) -> None:
        def delete(db: sqlite3.Connection) -> tuple[None, list[str]]:
            if not db.execute("SELECT 1 FROM maps WHERE name = ? AND (? IS NULL OR incarnation = ?)",
                              (name, incarnation, incarnation)).fetchall():
                return None, []
            files = [file for (file,) in db.execute(
                "SELECT file FROM batches WHERE map = ? AND file IS NOT NULL UNION ALL SELECT file FROM snapshots "
                "WHERE map = ? AND file IS NOT NULL UNION ALL SELECT file FROM bases WHERE map = ? AND file IS NOT NULL",
                (name, name, name))]
            db.execute("DELETE FROM maps WHERE name = ?", (name,))  # cascades to its batches and snapshots
            return None, files

        self._with_files([], delete)

    def append_batches(self, records: Sequence[BatchRecord]) -> list[int]:
        if not records:
            return []
        files: list[str | None] = []  # each record's file, None for one that goes in its row
        try:
            for r in records:
                files.append(self._stage(r.payload))
        except BaseException:
            self._files.remove(f for f in files if f is not None)
            raise
        crcs = [checksum(r.payload) for r in records]  # before the lock: 3 ms for 8 MB

        def append(db: sqlite3.Connection) -> tuple[list[int], list[str]]:
            versions = []
            for r, crc, file in zip(records, crcs, files, strict=True):
                taken = db.execute(f"UPDATE maps SET version = {_SQLITE_NEWEST} + 1, updated = ?, scans = scans + ?, "
                                   "history_bytes = history_bytes + ?, history_scans = history_scans + ? "
                                   "WHERE name = ? AND incarnation IS ? RETURNING version",
                                   (r.updated, r.scans, len(r.payload), r.scans, r.name, r.incarnation)).fetchall()
                if not taken:
                    raise MapGone(r.name)
                db.execute("INSERT INTO batches (map, seq, payload, crc, scans, updated, file, bytes, first_stamp) "
                           "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           (r.name, taken[0][0], r.payload if file is None else b"", crc, r.scans, r.updated, file,
                            len(r.payload), r.stamp_ns))
                versions.append(taken[0][0])
            return versions, []

        # one transaction, so one fsync of the WAL however many batches (group commit)
        return self._with_files([f for f in files if f is not None], append)

    def discard_batch(self, name: str, version: int, incarnation: str | None = None) -> None:
        def discard(db: sqlite3.Connection) -> tuple[None, list[str]]:
            if not db.execute("SELECT 1 FROM maps WHERE name = ? AND (? IS NULL OR incarnation = ?)",
                              (name, incarnation, incarnation)).fetchall():
                return None, []
            row = db.execute(f"SELECT scans, file, {BATCH_BYTES} FROM batches WHERE map = ? AND seq = ? "
                             "AND (length(payload) > 0 OR file IS NOT NULL)", (name, version)).fetchone()
            if row is None:  # already a tombstone, or folded into the base since
                return None, []
            db.execute("UPDATE batches SET payload = ?, crc = ?, scans = 0, file = NULL, bytes = 0 "
                       "WHERE map = ? AND seq = ?", (TOMBSTONE, checksum(TOMBSTONE), name, version))
            db.execute("UPDATE maps SET scans = scans - ?, history_bytes = history_bytes - ?, "
                       "history_scans = history_scans - ? WHERE name = ?", (row[0] or 0, row[2], row[0] or 0, name))
            return None, [] if row[1] is None else [row[1]]

        self._with_files([], discard)

    def write_snapshot(self, name: str, version: int, payload: bytes, incarnation: str | None = None) -> None:
        file = self._stage(payload)
        staged = [] if file is None else [file]
        crc = checksum(payload)

        def snapshot(db: sqlite3.Connection) -> tuple[None, list[str]]:
            row = db.execute("SELECT MAX(COALESCE(snapshot_version, 0), base_version, COALESCE((SELECT version FROM "
                             "snapshots WHERE map = maps.name), 0)) FROM maps "
                             "WHERE name = ? AND (? IS NULL OR incarnation = ?)", (name, incarnation, incarnation)).fetchone()
            # only forwards: another writer may have stored a newer one meanwhile (or folded it into the base)
            if row is None or row[0] >= version:
                return None, staged
            replaced = db.execute("SELECT file FROM snapshots WHERE map = ? AND file IS NOT NULL", (name,)).fetchall()
            _store_snapshot(db, name, version, payload, crc, file)
            return None, [f for (f,) in replaced]

        self._with_files(staged, snapshot)

    def fold_point(self, name: str, keep_bytes: int) -> int:
        with self._lock:
            head = self._db.execute("SELECT COALESCE(snapshot_version, 0) FROM maps WHERE name = ?", (name,)).fetchone()
            if head is None:
                return 0
            sizes = self._db.execute(f"SELECT seq, {BATCH_BYTES} FROM batches WHERE map = ? ORDER BY seq DESC",
                                     (name,))
            return fold_point_of(sizes, keep_bytes, head[0])

    def write_base(self, name: str, version: int, payload: bytes | None, incarnation: str | None = None,
                   planned_at: int | None = None) -> bool:
        file = None if payload is None else self._stage(payload)
        staged = [] if file is None else [file]
        crc = None if payload is None else checksum(payload)

        def fold(db: sqlite3.Connection) -> tuple[bool, list[str]]:
            row = db.execute("SELECT base_version, (SELECT version FROM snapshots WHERE map = maps.name) FROM maps "
                             "WHERE name = ? AND (? IS NULL OR incarnation = ?)", (name, incarnation, incarnation)).fetchone()
            if row is None or not may_fold(row[0], row[1], version, moving=payload is None) \
                    or corrections.blocks_fold(db.execute, name, planned_at):
                return False, staged
            dropped = [f for (f,) in db.execute("SELECT file FROM bases WHERE map = ? AND file IS NOT NULL UNION ALL "
                                                "SELECT file FROM batches WHERE map = ? AND seq <= ? AND file IS NOT NULL",
                                                (name, name, version))]
            # a moved restart snapshot keeps its file
            base = None if payload is None else (
                "INSERT INTO bases (map, version, payload, crc, updated, file) VALUES (?, ?, ?, ?, "
                "(SELECT updated FROM batches WHERE map = ? AND seq = ?), ?)",
                (name, version, payload if file is None else b"", crc, name, version, file))
            fold_rows(db.execute, name, version, base, "map, version, payload, crc, updated, file")
            return True, dropped

        return self._with_files(staged, fold)

    def put_correction(self, name: str, incarnation: str | None, correction_id: str, through_version: int,
                       payload: bytes, requested: str, owner: str, lease_until: float) -> None:
        self._transaction(lambda db: corrections.put(db.execute, name, incarnation, correction_id, through_version,
                                                     payload, requested, owner, lease_until))

    def correction(self, name: str, *, with_payload: bool = False) -> StoredCorrection | None:
        with self._lock:
            return corrections.read(self._db.execute, name, with_payload=with_payload)

    def correction_orphans(self, now: float) -> list[tuple[str, str]]:
        with self._lock:
            return corrections.orphans(self._db.execute, now)

    def claim_correction(self, name: str, correction_id: str, owner: str, lease_until: float, now: float) -> bool:
        return self._transaction(lambda db: corrections.claim(db.execute, name, correction_id, owner, lease_until, now))

    def report_correction(self, name: str, correction_id: str, owner: str, lease_until: float,
                          progress: dict[str, Any]) -> bool:
        return self._transaction(lambda db: corrections.report(db.execute, name, correction_id, owner, lease_until,
                                                               progress))

    def fail_correction(self, name: str, correction_id: str, progress: dict[str, Any]) -> None:
        self._transaction(lambda db: corrections.fail(db.execute, name, correction_id, progress))

    def switch_reposed(self, name: str, incarnation: str | None, change: Switch, snapshot: bytes) -> int | None:
        file = self._stage(snapshot)
        staged = [] if file is None else [file]
        crc = checksum(snapshot)

        def run(db: sqlite3.Connection) -> tuple[int | None, list[str]]:
            row = db.execute(f"SELECT {_SQLITE_NEWEST}, base_version FROM maps WHERE name = ? AND incarnation IS ?",
                             (name, incarnation)).fetchone()
            if row is None:
                raise MapGone(name)
            replaced = [f for (f,) in db.execute("SELECT file FROM snapshots WHERE map = ? AND file IS NOT NULL",
                                                 (name,))]
            version = corrections.switch(db.execute, name, int(row[0]), int(row[1]), change,
                                         lambda new: _store_snapshot(db, name, new, snapshot, crc, file))
            return version, staged if version is None else replaced

        return self._with_files(staged, run)

    def close(self) -> None:
        with self._lock:
            try:
                # fold the WAL back into the main file: a copied data dir is then the file and its payloads
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            except sqlite3.OperationalError:
                pass  # full or read-only: the WAL stays, and SQLite folds it in at the next open
            finally:
                self._db.close()
                self._files.detach()
