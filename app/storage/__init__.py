"""Durable map storage: a small interface, and an embedded SQLite implementation.

A map on disk is its metadata, at most one snapshot (the map's arrays at some
version) and the scan batches committed since that snapshot, in order. The
service commits a batch before it applies it and answers, so a batch that got a
200 survives ``kill -9``; a restart loads the snapshot and replays the batches
after it (fusion is deterministic, so the risk is bit for bit the same).

The store, not the service, gives each batch its version: several replicas of the
service may write one database (``app.storage.postgres``), and the map's row is what
orders their writes. A batch that could not be applied stays as a tombstone (an
empty payload), so a version once given out is never given again.

Payloads are opaque bytes here: storage knows nothing of scans or maps.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol, TypeVar

from app.errors import CommitUncertain, StorageUnavailable
from app.storage.payloadfiles import PayloadFiles, PayloadSource, PayloadUnreadable, Prefetched

T = TypeVar("T")

#: The SQLite store writes payloads (batches, snapshots) larger than this to files beside the database
#: (``app.storage.payloadfiles``), before the transaction and outside its lock: a commit of 8 MB held the other
#: maps' commits for 35-134 ms (issue 11). The group committer commits such batches alone, on a thread
#: of their own, for the same reason.
INLINE_BYTES = 256 * 1024


class NameTaken(Exception):
    """A map with this name is already stored."""


class MapGone(Exception):
    """The map is no longer stored under that name and incarnation (deleted, or deleted and created again)."""




def checksum(payload: bytes) -> int:
    """The CRC-32 stored with each payload (damage on disk is then found, not replayed)."""
    return zlib.crc32(payload)


#: A discarded batch: its row stays (its version is never given again) with no payload.
TOMBSTONE = b""


@dataclass
class StoredMap:
    """Everything stored about one map, or the part of it a loader was asked for."""

    name: str
    meta: dict[str, Any]
    updated: str
    snapshot_version: int = 0
    snapshot: bytes | None = None
    batches: list[tuple[int, bytes]] = field(default_factory=list)  # (version, payload), ascending, no tombstones
    damage: list[str] = field(default_factory=list)  # rows that failed their checksum: the map must not be served
    incarnation: str | None = None
    version: int = 0  # the newest committed version (tombstones included), whatever the loader returned
    #: version -> ``updated`` of that batch (or of the snapshot's version), where stored: the map's
    #: ``updated`` at that version, the same on every replica
    stamps: dict[int, str] = field(default_factory=dict)


@dataclass(frozen=True)
class MapHead:
    """A map's row without its payloads: what a replica compares with the version it holds."""

    name: str
    meta: dict[str, Any]
    updated: str
    version: int  # the newest committed, tombstones included
    snapshot_version: int
    scans: int  # scans of the stored batches (discarded ones excluded)
    incarnation: str | None


class BatchRecord(NamedTuple):
    """One batch to append to the map ``name`` of that ``incarnation``; the store gives it its version."""

    name: str
    incarnation: str | None
    payload: bytes
    updated: str  # the map's new ``updated``
    scans: int


class Storage(Protocol):
    """What the service needs from a store: SQLite (one process) or PostgreSQL (replicas sharing it).

    Every write method raises ``StorageUnavailable`` when the store cannot take the write;
    the store is then exactly as it was before the call.
    """

    def map_names(self) -> list[str]:
        """The names of the stored maps, sorted (a start loads them one at a time: ``load_map``)."""

    def map_head(self, name: str) -> MapHead | None:
        """The map's row (no payloads, one indexed query); None when there is none of that name."""

    def map_heads(self) -> list[MapHead]:
        """Every map's row, sorted by name."""

    def load_map(self, name: str) -> StoredMap | None:
        """One map with its snapshot and every batch after it; None when there is none of that name."""

    def load_since(self, name: str, after: int, up_to: int | None = None) -> StoredMap | None:
        """What a holder of the map at version ``after`` needs to reach ``up_to`` (None: the newest).

        When the stored snapshot is newer than ``after``: the snapshot and the batches after it;
        else no snapshot (``snapshot_version`` still says the stored one) and the batches after
        ``after``. Batches up to ``up_to`` only, ascending, without tombstones. The snapshot is
        carried even when it is newer than ``up_to`` (the batches before it are gone).
        """

    def create_map(self, name: str, meta: dict[str, Any], updated: str) -> None:
        """Store a new, empty map of incarnation ``meta.get("incarnation")``; ``NameTaken`` if the name is used."""

    def delete_map(self, name: str, incarnation: str | None = None) -> None:
        """Remove a map with its snapshot and batches; with ``incarnation``, only the map of that incarnation.

        No error when there is none.
        """

    def append_batches(self, records: Sequence[BatchRecord]) -> list[int]:
        """Durably store batches (of any maps) in one transaction, all or none; their versions, in their order.

        Each takes its map's next version. ``MapGone`` (nothing stored) when a record's map is not
        stored under that name and incarnation.
        """

    def discard_batch(self, name: str, version: int, incarnation: str | None = None) -> None:
        """Make a batch that could not be applied a tombstone: its version stays taken, its scans uncounted.

        With ``incarnation``, only in the map of that incarnation (no error otherwise).
        """

    def write_snapshot(self, name: str, version: int, payload: bytes, incarnation: str | None = None) -> None:
        """Store the map's state at ``version`` and drop the batches it covers, atomically.

        A no-op when the stored snapshot is as new or newer, or the map (of that incarnation) is gone.
        """

    def close(self) -> None:
        """Flush and release the store."""


_SCHEMA = """
CREATE TABLE IF NOT EXISTS maps (
    name TEXT PRIMARY KEY,
    meta TEXT NOT NULL,
    updated TEXT NOT NULL,
    version INTEGER,
    snapshot_version INTEGER,
    incarnation TEXT,
    scans INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS batches (
    map TEXT NOT NULL REFERENCES maps(name) ON DELETE CASCADE,
    seq INTEGER NOT NULL,
    payload BLOB NOT NULL,
    crc INTEGER,
    scans INTEGER,
    updated TEXT,
    file TEXT,
    PRIMARY KEY (map, seq)
);
CREATE TABLE IF NOT EXISTS snapshots (
    map TEXT PRIMARY KEY REFERENCES maps(name) ON DELETE CASCADE,
    version INTEGER NOT NULL,
    payload BLOB NOT NULL,
    crc INTEGER,
    updated TEXT,
    file TEXT
);
"""

#: Columns added since the first schema: an old database gets them (NULL, or the default) at open.
_ADDED_COLUMNS = {
    "maps": {"version": "INTEGER", "snapshot_version": "INTEGER", "incarnation": "TEXT",
             "scans": "INTEGER NOT NULL DEFAULT 0"},
    "batches": {"crc": "INTEGER", "scans": "INTEGER", "updated": "TEXT", "file": "TEXT"},
    "snapshots": {"crc": "INTEGER", "updated": "TEXT", "file": "TEXT"},
}

# A database from before the maps kept their versions has NULL there: its newest is read off its rows.
_SQLITE_NEWEST = ("COALESCE(maps.version, MAX(COALESCE(maps.snapshot_version, 0),"
                  " COALESCE((SELECT MAX(seq) FROM batches WHERE map = maps.name), 0),"
                  " COALESCE((SELECT version FROM snapshots WHERE map = maps.name), 0)))")
_SQLITE_HEAD = ("SELECT name, meta, updated, " + _SQLITE_NEWEST + ", COALESCE(maps.snapshot_version, "
                "(SELECT version FROM snapshots WHERE map = maps.name), 0), scans, incarnation FROM maps")

_SQLITE_CREATE = ("INSERT INTO maps (name, meta, updated, version, snapshot_version, incarnation, scans) "
                  "VALUES (?, ?, ?, 0, 0, ?, 0)")

#: What the loaders read first, in one query of either dialect (``?`` placeholders).
_LOAD_HEAD = ("SELECT meta, updated, version, snapshot_version, incarnation,"
             " (SELECT version FROM snapshots WHERE map = maps.name),"
             " (SELECT MAX(seq) FROM batches WHERE map = maps.name)"
             " FROM maps WHERE name = ?")
_NO_LIMIT = 2**62


def head_of(row: Sequence[Any]) -> MapHead:
    """A ``MapHead`` from (name, meta, updated, version, snapshot_version, scans, incarnation)."""
    return MapHead(row[0], json.loads(row[1]), row[2], int(row[3]), int(row[4]), int(row[5]), row[6])


def read_map(query: Callable[[str, tuple[Any, ...]], Iterable[Sequence[Any]]], name: str, after: int | None,
             up_to: int | None, files: PayloadSource | None = None) -> StoredMap | None:
    """``load_map`` (``after`` None) or ``load_since`` on a consistent view of a store: ``query(sql, args)``
    runs one statement of either dialect (``?`` placeholders) and yields its rows. ``files``: where the
    store keeps its big payloads (rows with a ``file`` column), if it does."""
    file_column = "file" if files is not None else "NULL"
    row = next(iter(query(_LOAD_HEAD, (name,))), None)
    if row is None:
        return None
    meta, updated, version, snapshot_version, incarnation, snapshot_row, newest_seq = row
    newest = max(snapshot_version or 0, snapshot_row or 0, newest_seq or 0)
    stored = StoredMap(name, json.loads(meta), updated, snapshot_version=snapshot_row or 0,
                       incarnation=incarnation, version=newest if version is None else version)
    if snapshot_row is not None and (after is None or snapshot_row > after):
        for snapshot in query(f"SELECT version, payload, crc, updated, {file_column} FROM snapshots WHERE map = ?",
                              (name,)):
            payload = _payload(stored, f"its snapshot (version {snapshot[0]})", snapshot[1], snapshot[4], files)
            if payload is not None:
                _take_snapshot(stored, snapshot[0], payload, snapshot[2])
            if snapshot[3] is not None:
                stored.stamps[snapshot[0]] = snapshot[3]
    lower = -_NO_LIMIT if after is None else max(after, snapshot_row or 0)
    # (a recorded snapshot whose row is gone is reported as such below, not again as the batches it held)
    previous = max(after or 0, snapshot_row or 0, snapshot_version or 0)
    for seq, stored_payload, crc, stamp, file in query(
            f"SELECT seq, payload, crc, updated, {file_column} FROM batches WHERE map = ? AND seq > ? AND seq <= ? "
            "ORDER BY seq", (name, lower, _NO_LIMIT if up_to is None else up_to)):
        _check_gap(stored, previous, seq, stamp)
        previous = seq
        payload = _payload(stored, f"its stored batch {seq}", stored_payload, file, files)
        if payload is not None:
            _take_batch(stored, seq, payload, crc)
        if stamp is not None:
            stored.stamps[seq] = stamp
    if up_to is not None and previous < up_to:  # a gap just below up_to shows only in the row above it
        for seq, stamp in query("SELECT seq, updated FROM batches WHERE map = ? AND seq > ? ORDER BY seq LIMIT 1",
                                (name, previous)):
            _check_gap(stored, previous, seq, stamp)
    _check_versions(stored, version, snapshot_version, snapshot_row or 0, newest_seq or 0)
    return stored


def _payload(stored: StoredMap, what: str, payload: bytes, file: str | None,
             files: PayloadSource | None) -> bytes | None:
    """A row's payload: its own bytes, or its file's; None (and damage) when the file is missing or unreadable."""
    if file is None or files is None:
        return bytes(payload)
    try:
        return files.read(file)
    except PayloadUnreadable as exc:
        stored.damage.append(f"{what}: {exc}")
        return None


def _check_gap(stored: StoredMap, previous: int, seq: int, stamp: str | None) -> None:
    """Damage if the row after version ``previous`` is ``seq`` > ``previous + 1``.

    Only before a row with its own stamp, written since discards became tombstones: nothing below
    it may be missing (before, a discarded batch's row was deleted, so an older row may follow a gap).
    """
    if stamp is not None and seq > previous + 1:
        stored.damage.append(f"its batches {previous + 1} to {seq - 1} are missing (the log jumps from "
                             f"version {previous} to {seq})")


def _take_snapshot(stored: StoredMap, version: int, payload: bytes, crc: int | None) -> None:
    if crc is not None and crc != checksum(payload):
        stored.damage.append(f"its snapshot (version {version}) fails its checksum")
    stored.snapshot_version, stored.snapshot = version, payload


def _take_batch(stored: StoredMap, seq: int, payload: bytes, crc: int | None) -> None:
    if crc is not None and crc != checksum(payload):
        stored.damage.append(f"its stored batch {seq} fails its checksum")
    elif payload == TOMBSTONE:
        return  # a discarded batch: nothing to replay (a damaged one is reported above, not skipped)
    stored.batches.append((seq, payload))


def _check_versions(stored: StoredMap, version: int | None, snapshot_version: int | None, snapshot_row: int,
                    newest_seq: int) -> None:
    """Rows deleted behind the service's back: the map's own record of its versions disagrees with its rows.

    (A deleted snapshot row left a map without batches 1-10 reporting version 12; a deleted last batch
    went unnoticed.) ``snapshot_row``/``newest_seq``: the stored snapshot's version and the newest
    batch row, tombstones included (0: none). NULL record: a database from before it, not checked
    until the next write.
    """
    if snapshot_version and snapshot_row != snapshot_version:
        stored.damage.append(f"its snapshot (version {snapshot_version}) is missing"
                             + (f"; version {snapshot_row} is stored" if snapshot_row else ""))
    newest = max(snapshot_row, newest_seq)
    if version is not None and newest < version:
        stored.damage.append(f"its batches up to version {version} are missing (the newest stored is {newest})")


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
            # an old database: its rows keep NULL there (a crc: not verifiable; a version: not checked until
            # the next write; an incarnation: matched by None), new ones get a value
            for table, added in _ADDED_COLUMNS.items():
                columns = {row[1] for row in self._db.execute(f"PRAGMA table_info({table})")}
                for column, declaration in added.items():
                    if column not in columns:
                        self._db.execute(f"ALTER TABLE {table} ADD COLUMN {column} {declaration}")
            # files of writes that never committed, or whose rows went before them, go (if no other store is open)
            self._files.attach(lambda: {file for (file,) in self._db.execute(
                "SELECT file FROM batches WHERE file IS NOT NULL UNION SELECT file FROM snapshots WHERE file IS NOT NULL")})

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

    def _load(self, name: str, after: int | None, up_to: int | None) -> StoredMap | None:
        """``read_map`` with the map's payload files read between two holds of the lock, not under it: 256 MiB
        of log read for an MCAP export held every map's commits for as long.

        The files' names are read under the lock, the files after it; the rows are then read in one
        view (a file named by a row committed in between is read then; one removed in between belongs
        to no row any more).
        """
        lower = -_NO_LIMIT if after is None else after
        with self._lock:
            names = [file for (file,) in self._db.execute(
                "SELECT file FROM batches WHERE map = ? AND seq > ? AND seq <= ? AND file IS NOT NULL UNION ALL "
                "SELECT file FROM snapshots WHERE map = ? AND version > ? AND file IS NOT NULL",
                (name, lower, _NO_LIMIT if up_to is None else up_to, name, lower))]
        files = Prefetched(self._files, names)
        with self._lock:  # one connection, so no write comes between the queries
            return read_map(self._db.execute, name, after, up_to, files)

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
                "SELECT file FROM batches WHERE map = ? AND file IS NOT NULL "
                "UNION ALL SELECT file FROM snapshots WHERE map = ? AND file IS NOT NULL", (name, name))]
            db.execute("DELETE FROM maps WHERE name = ?", (name,))  # cascades to its batches and snapshot
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
                taken = db.execute(f"UPDATE maps SET version = {_SQLITE_NEWEST} + 1, updated = ?, scans = scans + ? "
                                   "WHERE name = ? AND incarnation IS ? RETURNING version",
                                   (r.updated, r.scans, r.name, r.incarnation)).fetchall()
                if not taken:
                    raise MapGone(r.name)
                db.execute("INSERT INTO batches (map, seq, payload, crc, scans, updated, file) "
                           "VALUES (?, ?, ?, ?, ?, ?, ?)",
                           (r.name, taken[0][0], r.payload if file is None else b"", crc, r.scans, r.updated, file))
                versions.append(taken[0][0])
            return versions, []

        # one transaction, so one fsync of the WAL however many batches (group commit)
        return self._with_files([f for f in files if f is not None], append)

    def discard_batch(self, name: str, version: int, incarnation: str | None = None) -> None:
        def discard(db: sqlite3.Connection) -> tuple[None, list[str]]:
            if not db.execute("SELECT 1 FROM maps WHERE name = ? AND (? IS NULL OR incarnation = ?)",
                              (name, incarnation, incarnation)).fetchall():
                return None, []
            row = db.execute("SELECT scans, file FROM batches WHERE map = ? AND seq = ? "
                             "AND (length(payload) > 0 OR file IS NOT NULL)", (name, version)).fetchone()
            if row is None:  # already a tombstone, or covered by a snapshot since
                return None, []
            db.execute("UPDATE batches SET payload = ?, crc = ?, scans = 0, file = NULL WHERE map = ? AND seq = ?",
                       (TOMBSTONE, checksum(TOMBSTONE), name, version))
            db.execute("UPDATE maps SET scans = scans - ? WHERE name = ?", (row[0] or 0, name))
            return None, [] if row[1] is None else [row[1]]

        self._with_files([], discard)

    def write_snapshot(self, name: str, version: int, payload: bytes, incarnation: str | None = None) -> None:
        file = self._stage(payload)
        staged = [] if file is None else [file]
        crc = checksum(payload)

        def snapshot(db: sqlite3.Connection) -> tuple[None, list[str]]:
            if not db.execute("SELECT 1 FROM maps WHERE name = ? AND (? IS NULL OR incarnation = ?)",
                              (name, incarnation, incarnation)).fetchall():
                return None, staged
            replaced = db.execute("SELECT file FROM snapshots WHERE map = ? AND file IS NOT NULL", (name,)).fetchall()
            # only forwards: another writer may have stored a newer one meanwhile
            # the snapshot keeps its version's ``updated`` (its batch row goes)
            if not db.execute("INSERT INTO snapshots (map, version, payload, crc, updated, file) VALUES (?, ?, ?, ?, "
                              "(SELECT updated FROM batches WHERE map = ? AND seq = ?), ?) "
                              "ON CONFLICT(map) DO UPDATE SET version = excluded.version, "
                              "payload = excluded.payload, crc = excluded.crc, updated = excluded.updated, "
                              "file = excluded.file WHERE snapshots.version < excluded.version RETURNING version",
                              (name, version, payload if file is None else b"", crc, name, version, file)).fetchall():
                return None, staged
            covered = [f for (f,) in db.execute("SELECT file FROM batches WHERE map = ? AND seq <= ? "
                                                "AND file IS NOT NULL", (name, version))]
            db.execute("DELETE FROM batches WHERE map = ? AND seq <= ?", (name, version))
            db.execute("UPDATE maps SET snapshot_version = ? WHERE name = ?", (version, name))
            return None, covered + [f for (f,) in replaced]

        self._with_files(staged, snapshot)

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
