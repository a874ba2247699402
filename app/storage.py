"""Durable map storage: a small interface, and an embedded SQLite implementation.

A map on disk is its metadata, at most one snapshot (the map's arrays at some
version) and the scan batches acknowledged since that snapshot, in order. The
service commits a batch before it applies it and answers, so a batch that got a
200 survives ``kill -9``; a restart loads the snapshot and replays the batches
after it (fusion is deterministic, so the risk is bit for bit the same).

Payloads are opaque bytes here: storage knows nothing of scans or maps.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol


class NameTaken(Exception):
    """A map with this name is already stored."""


class StorageUnavailable(Exception):
    """A write could not be made durable (disk full, read-only or failing data directory); nothing was stored."""


def _crc(payload: bytes) -> int:
    return zlib.crc32(payload)


@dataclass
class StoredMap:
    """Everything stored about one map."""

    name: str
    meta: dict[str, Any]
    updated: str
    snapshot_version: int = 0
    snapshot: bytes | None = None
    batches: list[tuple[int, bytes]] = field(default_factory=list)  # (version, payload), ascending
    damage: list[str] = field(default_factory=list)  # rows that failed their checksum: the map must not be served


class BatchRecord(NamedTuple):
    """One batch to append: the map, the version it brings the map to, its payload, the map's new ``updated``."""

    name: str
    version: int
    payload: bytes
    updated: str


class Storage(Protocol):
    """What the service needs from a store; another backend (a shared database) can replace SQLite."""

    def map_names(self) -> list[str]:
        """The names of the stored maps, sorted (a start loads them one at a time: ``load_map``)."""

    def load_map(self, name: str) -> StoredMap | None:
        """One map with its latest snapshot and the batches after it; None when there is none of that name."""

    def create_map(self, name: str, meta: dict[str, Any], updated: str) -> None:
        """Store a new, empty map; ``NameTaken`` if the name is used."""

    def delete_map(self, name: str) -> None:
        """Remove a map with its snapshot and batches (no error when absent)."""

    def append_batch(self, name: str, version: int, payload: bytes, updated: str) -> None:
        """Durably store the batch that brings ``name`` to ``version`` before returning.

        Every write method raises ``StorageUnavailable`` when the store cannot take the write;
        the store is then exactly as it was before the call.
        """

    def append_batches(self, batches: Sequence[BatchRecord]) -> None:
        """Durably store several batches (of any maps) in one transaction: all of them or none."""

    def discard_batch(self, name: str, version: int) -> None:
        """Forget a batch that could not be applied (it was never acknowledged)."""

    def write_snapshot(self, name: str, version: int, payload: bytes) -> None:
        """Store the map state at ``version`` and drop the batches it covers, atomically."""

    def close(self) -> None:
        """Flush and release the store."""


_SCHEMA = """
CREATE TABLE IF NOT EXISTS maps (
    name TEXT PRIMARY KEY,
    meta TEXT NOT NULL,
    updated TEXT NOT NULL,
    version INTEGER,
    snapshot_version INTEGER
);
CREATE TABLE IF NOT EXISTS batches (
    map TEXT NOT NULL REFERENCES maps(name) ON DELETE CASCADE,
    seq INTEGER NOT NULL,
    payload BLOB NOT NULL,
    crc INTEGER,
    PRIMARY KEY (map, seq)
);
CREATE TABLE IF NOT EXISTS snapshots (
    map TEXT PRIMARY KEY REFERENCES maps(name) ON DELETE CASCADE,
    version INTEGER NOT NULL,
    payload BLOB NOT NULL,
    crc INTEGER
);
"""


def _take_snapshot(stored: StoredMap, version: int, payload: bytes, crc: int | None) -> None:
    if crc is not None and crc != _crc(payload):
        stored.damage.append(f"its snapshot (version {version}) fails its checksum")
    stored.snapshot_version, stored.snapshot = version, payload


def _take_batch(stored: StoredMap, seq: int, payload: bytes, crc: int | None) -> None:
    if crc is not None and crc != _crc(payload):
        stored.damage.append(f"its stored batch {seq} fails its checksum")
    stored.batches.append((seq, payload))


def _check_versions(stored: StoredMap, version: int | None, snapshot_version: int | None) -> None:
    """Rows deleted behind the service's back: the map's own record of its versions disagrees with its rows.

    (A deleted snapshot row left a map without batches 1-10 reporting version 12; a deleted last batch
    went unnoticed.) NULL: a database from before the record, not checked until the next write.
    """
    if snapshot_version and stored.snapshot_version != snapshot_version:
        stored.damage.append(f"its snapshot (version {snapshot_version}) is missing"
                             + (f"; version {stored.snapshot_version} is stored" if stored.snapshot else ""))
    newest = max([stored.snapshot_version, *(seq for seq, _ in stored.batches)])
    if version is not None and newest < version:
        stored.damage.append(f"its batches up to version {version} are missing (the newest stored is {newest})")


class SqliteStorage:
    """``Storage`` in one SQLite file: WAL journal, ``synchronous=FULL`` (fsync at every commit).

    One connection shared by the service's threads behind a lock: SQLite has one
    writer at a time anyway, and the commits are short next to fusion.
    """

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        # isolation_level=None: transactions are opened explicitly, so each method is one commit
        self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            self._db.executescript(_SCHEMA)
            for table in ("batches", "snapshots"):
                # a database from before the checksums: its rows keep a NULL crc (not verifiable), new ones get one
                columns = {row[1] for row in self._db.execute(f"PRAGMA table_info({table})")}
                if "crc" not in columns:
                    self._db.execute(f"ALTER TABLE {table} ADD COLUMN crc INTEGER")
            # a database from before the maps kept their versions: NULL (not checked) until the next write
            columns = {row[1] for row in self._db.execute("PRAGMA table_info(maps)")}
            for column in ("version", "snapshot_version"):
                if column not in columns:
                    self._db.execute(f"ALTER TABLE maps ADD COLUMN {column} INTEGER")

    def _write(self, statements: list[tuple[str, tuple[Any, ...]]]) -> None:
        """Run statements in one immediate transaction: all of them are on disk when this returns.

        ``StorageUnavailable`` (nothing written) when SQLite cannot write: a full disk, a
        read-only directory or an I/O error, at any statement or at the COMMIT itself.
        """
        with self._lock:
            if self._db.in_transaction:  # left open by a ROLLBACK that failed too
                self._rollback()
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    for sql, args in statements:
                        self._db.execute(sql, args)
                    # inside the try: a COMMIT that fails (SQLITE_FULL at the WAL append) leaves
                    # the transaction open, and the next BEGIN would fail on it
                    self._db.execute("COMMIT")
                except BaseException:
                    self._rollback()
                    raise
            except sqlite3.OperationalError as exc:
                raise StorageUnavailable(f"{exc} (SQLite {getattr(exc, 'sqlite_errorname', '?')})") from exc

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

    def load_map(self, name: str) -> StoredMap | None:
        with self._lock:
            row = self._db.execute("SELECT meta, updated, version, snapshot_version FROM maps WHERE name = ?",
                                   (name,)).fetchone()
            if row is None:
                return None
            stored = StoredMap(name, json.loads(row[0]), row[1])
            snapshot = self._db.execute("SELECT version, payload, crc FROM snapshots WHERE map = ?",
                                        (name,)).fetchone()
            if snapshot is not None:
                _take_snapshot(stored, snapshot[0], bytes(snapshot[1]), snapshot[2])
            for seq, payload, crc in self._db.execute(
                    "SELECT seq, payload, crc FROM batches WHERE map = ? ORDER BY seq", (name,)):
                _take_batch(stored, seq, bytes(payload), crc)
        _check_versions(stored, row[2], row[3])
        return stored

    def create_map(self, name: str, meta: dict[str, Any], updated: str) -> None:
        try:
            self._write([("INSERT INTO maps (name, meta, updated, version, snapshot_version) VALUES (?, ?, ?, 0, 0)",
                          (name, json.dumps(meta), updated))])
        except sqlite3.IntegrityError:
            raise NameTaken(name) from None

    def delete_map(self, name: str) -> None:
        # the foreign keys cascade to the map's batches and snapshot
        self._write([("DELETE FROM maps WHERE name = ?", (name,))])

    def append_batch(self, name: str, version: int, payload: bytes, updated: str) -> None:
        self.append_batches([BatchRecord(name, version, payload, updated)])

    def append_batches(self, batches: Sequence[BatchRecord]) -> None:
        # one transaction, so one fsync of the WAL however many batches (group commit)
        statements: list[tuple[str, tuple[Any, ...]]] = []
        for b in batches:
            statements.append(("INSERT INTO batches (map, seq, payload, crc) VALUES (?, ?, ?, ?)",
                               (b.name, b.version, b.payload, _crc(b.payload))))
            statements.append(("UPDATE maps SET updated = ?, version = MAX(COALESCE(version, 0), ?) WHERE name = ?",
                               (b.updated, b.version, b.name)))
        self._write(statements)

    def discard_batch(self, name: str, version: int) -> None:
        self._write([
            ("DELETE FROM batches WHERE map = ? AND seq = ?", (name, version)),
            # the newest stored row is the map's version again (it was this batch when no later one committed)
            ("UPDATE maps SET version = COALESCE((SELECT MAX(seq) FROM batches WHERE map = ?), snapshot_version, 0) "
             "WHERE name = ? AND version = ?", (name, name, version)),
        ])

    def write_snapshot(self, name: str, version: int, payload: bytes) -> None:
        self._write(
            [
                (
                    "INSERT INTO snapshots (map, version, payload, crc) VALUES (?, ?, ?, ?) "
                    "ON CONFLICT(map) DO UPDATE SET version = excluded.version, payload = excluded.payload, "
                    "crc = excluded.crc",
                    (name, version, payload, _crc(payload)),
                ),
                ("DELETE FROM batches WHERE map = ? AND seq <= ?", (name, version)),
                ("UPDATE maps SET snapshot_version = ? WHERE name = ?", (version, name)),
            ]
        )

    def close(self) -> None:
        with self._lock:
            try:
                # fold the WAL back into the main file so a copied data dir is one self-contained file
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            except sqlite3.OperationalError:
                pass  # full or read-only: the WAL stays, and SQLite folds it in at the next open
            finally:
                self._db.close()
