"""``Storage`` in PostgreSQL: several replicas of the service share one database.

The tables are SQLite's (``app.storage.sqlite``): meta as JSON text, payloads as ``bytea``,
CRC-32 checksums. What makes sharing safe is the ``maps`` row: every write to a
map (append, discard, snapshot, delete) locks that row first, so two replicas'
writes to one map are serialized there, and ``maps.version + 1`` gives each batch
its version without gaps. A group commit locks its maps in name order, so two
replicas committing the same maps never deadlock.

Only this module imports psycopg (the ``postgres`` extra): the SQLite default does not need it.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

import psycopg
import psycopg.errors
from psycopg_pool import ConnectionPool

from app.storage import corrections
from app.storage.corrections import StoredCorrection, Switch
from app.storage.base import (
    BATCH_BYTES,
    HISTORY_FROM_STAMP,
    HISTORY_OF_ROWS,
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
)

#: ``pg_advisory_xact_lock`` key held while the schema is created: replicas starting at once would
#: otherwise race in ``CREATE TABLE IF NOT EXISTS`` (a unique violation in the catalog).
SCHEMA_LOCK = 0x66757A7A79  # "fuzzy"

T = TypeVar("T")

_SCHEMA = (
    """CREATE TABLE IF NOT EXISTS maps (
        name TEXT PRIMARY KEY,
        meta TEXT NOT NULL,
        updated TEXT NOT NULL,
        version BIGINT NOT NULL DEFAULT 0,
        snapshot_version BIGINT NOT NULL DEFAULT 0,
        incarnation TEXT,
        scans BIGINT NOT NULL DEFAULT 0
    )""",
    """CREATE TABLE IF NOT EXISTS batches (
        map TEXT NOT NULL REFERENCES maps(name) ON DELETE CASCADE,
        seq BIGINT NOT NULL,
        payload BYTEA NOT NULL,
        crc BIGINT,
        scans INTEGER,
        updated TEXT,
        PRIMARY KEY (map, seq)
    )""",
    *(f"""CREATE TABLE IF NOT EXISTS {table} (
        map TEXT PRIMARY KEY REFERENCES maps(name) ON DELETE CASCADE,
        version BIGINT NOT NULL,
        payload BYTEA NOT NULL,
        crc BIGINT,
        updated TEXT
    )""" for table in ("snapshots", "bases")),  # a map's restart snapshot and its base snapshot
)
#: Columns added since the first schema (a database from before gets them, its history counted from its rows):
#: (table, column, definition). Each is added only when missing: ``ALTER TABLE ... ADD COLUMN IF NOT EXISTS`` takes
#: the table's ACCESS EXCLUSIVE lock even when the column is there, and a replica starting beside one that writes
#: then deadlocked with it (PostgreSQL 40P01, a batch answered 503).
_ADDED_COLUMNS = (
    ("maps", "base_version", "BIGINT NOT NULL DEFAULT 0"),
    ("maps", "history_bytes", "BIGINT NOT NULL DEFAULT 0"),
    ("maps", "history_scans", "BIGINT NOT NULL DEFAULT 0"),
    ("batches", "bytes", "BIGINT"),
    ("batches", "poses", "BYTEA"),
    ("batches", "first_stamp", "BIGINT"),
)

_HEAD = ("SELECT name, meta, updated, version, snapshot_version, scans, incarnation, base_version, history_bytes, "
         "history_scans, " + HISTORY_FROM_STAMP + " FROM maps")
# one round trip per batch: the UPDATE takes the map's row lock and its next version, the INSERT uses it;
# no row when the map is not stored under that name and incarnation
_APPEND = """WITH taken AS (
    UPDATE maps SET version = version + 1, updated = %(updated)s, scans = scans + %(scans)s,
        history_bytes = history_bytes + %(bytes)s, history_scans = history_scans + %(scans)s
    WHERE name = %(name)s AND incarnation IS NOT DISTINCT FROM %(incarnation)s::text
    RETURNING name, version)
INSERT INTO batches (map, seq, payload, crc, scans, updated, bytes, first_stamp)
SELECT name, version, %(payload)b, %(crc)s, %(scans)s, %(updated)s, %(bytes)s, %(stamp)s::bigint FROM taken RETURNING seq"""
_LOCK_MAP = "SELECT 1 FROM maps WHERE name = %s AND (%s::text IS NULL OR incarnation = %s) FOR UPDATE"


class PostgresStorage:
    """``Storage`` on a PostgreSQL database shared by the service's replicas (psycopg 3, a small pool).

    ``StorageUnavailable`` for any failure to reach the database or to write durably (reads
    too: a replica without its database cannot answer). A connection lost during COMMIT is
    ambiguous: the transaction may have committed although the call raised.
    """

    def __init__(self, url: str, *, min_connections: int = 1, max_connections: int = 4,
                 timeout: float = 10.0) -> None:
        # autocommit: a lone read (map_head, before every read) is one round trip, no BEGIN/COMMIT;
        # writes open their transaction explicitly
        self._pool = ConnectionPool(url, min_size=min_connections, max_size=max_connections, timeout=timeout,
                                    kwargs={"autocommit": True}, open=False, name="fuzzyrisk")
        try:
            try:
                self._pool.open(wait=True, timeout=timeout)
            except psycopg.OperationalError as exc:  # PoolTimeout: the database cannot be reached
                raise StorageUnavailable(f"{exc} (PostgreSQL connection)") from exc
            with self._connection() as conn, conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (SCHEMA_LOCK,))
                counted = conn.execute("SELECT 1 FROM information_schema.columns WHERE table_schema = current_schema() "
                                       "AND table_name = 'maps' AND column_name = 'history_bytes'").fetchone()
                for statement in _SCHEMA:
                    conn.execute(statement)
                conn.execute(corrections.SCHEMA.format(blob="BYTEA", int="BIGINT", real="DOUBLE PRECISION"))
                present = {(str(t), str(c)) for t, c in conn.execute(
                    "SELECT table_name, column_name FROM information_schema.columns WHERE table_schema = current_schema()")}
                for table, column, definition in _ADDED_COLUMNS:
                    if (table, column) not in present:
                        conn.execute(f"ALTER TABLE {table} ADD COLUMN {column} {definition}")
                if counted is None:  # a database from before the history: it holds the batches after the snapshots
                    conn.execute(f"UPDATE maps SET (history_bytes, history_scans) = {HISTORY_OF_ROWS}")
        except BaseException:
            self._pool.close()
            raise

    @contextmanager
    def _connection(self) -> Iterator[psycopg.Connection[Any]]:
        """A pooled connection; the database's failures (unreachable, cannot write) as ``StorageUnavailable``."""
        used: psycopg.Connection[Any] | None = None
        try:
            with self._pool.connection() as conn:
                used = conn
                yield conn
        except (psycopg.OperationalError, psycopg.errors.ReadOnlySqlTransaction) as exc:
            # OperationalError: connection lost or refused, no connection free in time (PoolTimeout), disk
            # full, server shutting down, deadlock; read-only: a standby after a failover
            if used is not None and used.broken:
                # closed by the server (a restart, a failover): the idle ones in the pool are too, most
                # likely; replaced now, they do not fail the next calls one by one
                self._pool.check()
            raise StorageUnavailable(f"{exc} (PostgreSQL {exc.sqlstate or 'connection'})") from exc

    def _read(self, work: Callable[[psycopg.Connection[Any]], T]) -> T:
        """``work`` on a pooled connection, once more on another when that one turns out dead.

        A pooled connection that the server closed (a restart, a failover, an idle timeout) fails
        at its next use; a read is safe to run again, a write is not (it may have committed).
        """
        used: list[psycopg.Connection[Any]] = []

        def run() -> T:
            with self._connection() as conn:
                used.append(conn)
                return work(conn)

        try:
            return run()
        except StorageUnavailable:
            if not used or not used[-1].broken:
                raise
            return run()

    def map_names(self) -> list[str]:
        # COLLATE "C": sorted as Python and SQLite sort, whatever the database's locale
        return self._read(lambda conn: [name for (name,) in conn.execute(
            'SELECT name FROM maps ORDER BY name COLLATE "C"')])

    def map_head(self, name: str) -> MapHead | None:
        row = self._read(lambda conn: conn.execute(_HEAD + " WHERE name = %s", (name,)).fetchone())
        return None if row is None else head_of(row)

    def map_heads(self) -> list[MapHead]:
        rows = self._read(lambda conn: conn.execute(_HEAD + ' ORDER BY name COLLATE "C"').fetchall())
        return [head_of(row) for row in rows]

    def load_map(self, name: str) -> StoredMap | None:
        return self._read(lambda conn: _consistent_read(conn, name, None, None))

    def load_since(self, name: str, after: int, up_to: int | None = None) -> StoredMap | None:
        return self._read(lambda conn: _consistent_read(conn, name, after, up_to))

    def load_history(self, name: str, up_to: int | None = None, after: int | None = None) -> StoredMap | None:
        return self._read(lambda conn: _consistent_read(conn, name, after, up_to, from_base=True))

    def create_map(self, name: str, meta: dict[str, Any], updated: str) -> None:
        try:
            with self._connection() as conn:
                conn.execute("INSERT INTO maps (name, meta, updated, incarnation) VALUES (%s, %s, %s, %s)",
                             (name, json.dumps(meta), updated, meta.get("incarnation")))
        except psycopg.errors.UniqueViolation:
            raise NameTaken(name) from None

    def delete_map(self, name: str, incarnation: str | None = None) -> None:
        # the foreign keys cascade to the map's batches and snapshot; the row lock waits for a write under way
        with self._connection() as conn:
            conn.execute("DELETE FROM maps WHERE name = %s AND (%s::text IS NULL OR incarnation = %s)",
                         (name, incarnation, incarnation))

    def append_batches(self, records: Sequence[BatchRecord]) -> list[int]:
        if not records:
            return []
        # maps locked in name order (a stable sort keeps each map's own order): no deadlock between replicas
        order = sorted(range(len(records)), key=lambda i: records[i].name)
        params = [{"name": records[i].name, "incarnation": records[i].incarnation, "payload": records[i].payload,
                   "crc": checksum(records[i].payload), "updated": records[i].updated, "scans": records[i].scans,
                   "bytes": len(records[i].payload), "stamp": records[i].stamp_ns}
                  for i in order]
        versions = [0] * len(records)
        committing = False
        try:
            # one transaction, so one WAL flush however many batches (group commit); executemany pipelines them
            with self._connection() as conn, conn.transaction(), conn.cursor() as cur:
                cur.executemany(_APPEND, params, returning=True)
                for i in order:
                    row = cur.fetchone()
                    if row is None:
                        raise MapGone(records[i].name)  # rolls the whole group back
                    versions[i] = row[0]
                    cur.nextset()
                committing = True  # the transaction's exit sends COMMIT
        except StorageUnavailable as exc:
            if committing:  # the server may have committed before the connection went
                raise CommitUncertain(str(exc)) from exc
            raise
        return versions

    def discard_batch(self, name: str, version: int, incarnation: str | None = None) -> None:
        with self._connection() as conn, conn.transaction():
            if conn.execute(_LOCK_MAP, (name, incarnation, incarnation)).fetchone() is None:
                return
            row = conn.execute(f"SELECT scans, {BATCH_BYTES} FROM batches WHERE map = %s AND seq = %s "
                               "AND length(payload) > 0", (name, version)).fetchone()
            if row is None:  # already a tombstone, or folded into the base since
                return
            conn.execute("UPDATE batches SET payload = %b, crc = %s, scans = 0, bytes = 0 WHERE map = %s AND seq = %s",
                         (TOMBSTONE, checksum(TOMBSTONE), name, version))
            conn.execute("UPDATE maps SET scans = scans - %s, history_bytes = history_bytes - %s, "
                         "history_scans = history_scans - %s WHERE name = %s", (row[0] or 0, row[1], row[0] or 0, name))

    def write_snapshot(self, name: str, version: int, payload: bytes, incarnation: str | None = None) -> None:
        with self._connection() as conn, conn.transaction():
            # the map's row lock first, as every write takes it: two replicas' snapshots of a map go one at a time
            row = conn.execute("SELECT GREATEST(snapshot_version, base_version) FROM maps WHERE name = %s "
                               "AND (%s::text IS NULL OR incarnation = %s) FOR UPDATE",
                               (name, incarnation, incarnation)).fetchone()
            if row is None or row[0] >= version:
                return  # as new or newer already stored (another replica's), or folded into the base
            _store_snapshot(conn, name, version, payload)

    def fold_point(self, name: str, keep_bytes: int) -> int:
        def point(conn: psycopg.Connection[Any]) -> int:
            with conn.transaction():
                conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY")
                head = conn.execute("SELECT snapshot_version FROM maps WHERE name = %s", (name,)).fetchone()
                if head is None:
                    return 0
                sizes = conn.execute(f"SELECT seq, {BATCH_BYTES} FROM batches WHERE map = %s ORDER BY seq DESC",
                                     (name,))
                return fold_point_of(sizes, keep_bytes, head[0])

        return self._read(point)

    def write_base(self, name: str, version: int, payload: bytes | None, incarnation: str | None = None,
                   planned_at: int | None = None) -> bool:
        with self._connection() as conn, conn.transaction():
            # under the map's row lock, as every write: the first replica to fold does it, the others find it done
            row = conn.execute("SELECT base_version, (SELECT version FROM snapshots WHERE map = maps.name) FROM maps "
                               "WHERE name = %s AND (%s::text IS NULL OR incarnation = %s) FOR UPDATE",
                               (name, incarnation, incarnation)).fetchone()
            if row is None or not may_fold(row[0], row[1], version, moving=payload is None) \
                    or corrections.blocks_fold(_dialect(conn), name, planned_at):
                return False
            base = None if payload is None else (
                "INSERT INTO bases (map, version, payload, crc, updated) VALUES (?, ?, ?, ?, "
                "(SELECT updated FROM batches WHERE map = ? AND seq = ?))",
                (name, version, payload, checksum(payload), name, version))
            fold_rows(lambda sql, args: conn.execute(sql.replace("?", "%s"), args), name, version, base,
                      "map, version, payload, crc, updated")
            return True

    def put_correction(self, name: str, incarnation: str | None, correction_id: str, through_version: int,
                       payload: bytes, requested: str, owner: str, lease_until: float) -> None:
        with self._connection() as conn, conn.transaction():
            conn.execute(_LOCK_MAP, (name, incarnation, incarnation))  # the map's row lock, as every write
            corrections.put(_dialect(conn), name, incarnation, correction_id, through_version, payload, requested,
                            owner, lease_until)

    def correction(self, name: str, *, with_payload: bool = False) -> StoredCorrection | None:
        return self._read(lambda conn: corrections.read(_dialect(conn), name, with_payload=with_payload))

    def correction_orphans(self, now: float) -> list[tuple[str, str]]:
        return self._read(lambda conn: corrections.orphans(_dialect(conn), now))

    def claim_correction(self, name: str, correction_id: str, owner: str, lease_until: float, now: float) -> bool:
        with self._connection() as conn:
            return corrections.claim(_dialect(conn), name, correction_id, owner, lease_until, now)

    def report_correction(self, name: str, correction_id: str, owner: str, lease_until: float,
                          progress: dict[str, Any]) -> bool:
        with self._connection() as conn:
            return corrections.report(_dialect(conn), name, correction_id, owner, lease_until, progress)

    def fail_correction(self, name: str, correction_id: str, progress: dict[str, Any]) -> None:
        with self._connection() as conn:
            corrections.fail(_dialect(conn), name, correction_id, progress)

    def switch_reposed(self, name: str, incarnation: str | None, change: Switch, snapshot: bytes) -> int | None:
        committing = False
        try:
            with self._connection() as conn, conn.transaction():
                row = conn.execute("SELECT version, base_version FROM maps WHERE name = %s "
                                   "AND incarnation IS NOT DISTINCT FROM %s::text FOR UPDATE",
                                   (name, incarnation)).fetchone()
                if row is None:
                    raise MapGone(name)

                version = corrections.switch(_dialect(conn), name, int(row[0]), int(row[1]), change,
                                             lambda new: _store_snapshot(conn, name, new, snapshot))
                committing = version is not None
                return version
        except StorageUnavailable as exc:
            if committing:  # the server may have committed before the connection went
                raise CommitUncertain(str(exc)) from exc
            raise

    def close(self) -> None:
        self._pool.close()


def _store_snapshot(conn: psycopg.Connection[Any], name: str, version: int, payload: bytes) -> None:
    """The map's restart snapshot row replaced by ``payload`` at ``version``, with that version's batch's ``updated``."""
    conn.execute("INSERT INTO snapshots (map, version, payload, crc, updated) VALUES (%s, %s, %b, %s, "
                 "(SELECT updated FROM batches WHERE map = %s AND seq = %s)) "
                 "ON CONFLICT (map) DO UPDATE SET version = excluded.version, "
                 "payload = excluded.payload, crc = excluded.crc, updated = excluded.updated",
                 (name, version, payload, checksum(payload), name, version))
    conn.execute("UPDATE maps SET snapshot_version = %s WHERE name = %s", (version, name))


def _dialect(conn: psycopg.Connection[Any]) -> corrections.Execute:
    """``execute`` with the shared statements' ``?`` placeholders."""
    return lambda sql, args: conn.execute(sql.replace("?", "%s"), args)


def _consistent_read(conn: psycopg.Connection[Any], name: str, after: int | None,
                     up_to: int | None, *, from_base: bool = False) -> StoredMap | None:
    """``read_map`` in a read-only REPEATABLE READ transaction: its queries see one state of the database
    (a snapshot that another replica writes between them must not look like missing batches)."""
    with conn.transaction(), conn.cursor(binary=True) as cur:
        cur.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY")

        def query(sql: str, args: tuple[Any, ...]) -> Iterable[Sequence[Any]]:
            return cur.execute(sql.replace("?", "%s"), args).fetchall()  # read_map's placeholders are ``?``

        return read_map(query, name, after, up_to, from_base=from_base)
