"""What both stores share: the ``Storage`` protocol, its records and errors, and the reader of a map's rows.

``SqliteStorage`` (``app.storage.sqlite``) and ``PostgresStorage`` (``app.storage.postgres``) implement
``Storage`` over the same tables, and load a map with the same ``read_map`` (``?`` placeholders, either dialect).
``CommitUncertain`` and ``StorageUnavailable`` (``app.errors``) are re-exported: the errors a store raises.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

from app.errors import CommitUncertain, StorageUnavailable
from app.storage.payloadfiles import PayloadSource, PayloadUnreadable

if TYPE_CHECKING:
    from app.storage.corrections import StoredCorrection, Switch

__all__ = [
    "INLINE_BYTES",
    "NO_LIMIT",
    "TOMBSTONE",
    "BatchRecord",
    "CommitUncertain",
    "MapGone",
    "MapHead",
    "NameTaken",
    "Storage",
    "StorageUnavailable",
    "StoredMap",
    "checksum",
    "head_of",
    "read_map",
]

#: The SQLite store writes payloads (batches, snapshots) larger than this to files beside the database
#: (``app.storage.payloadfiles``), before the transaction and outside its lock: a commit of 8 MB held the other
#: maps' commits for 35-134 ms. The group committer commits such batches alone, on a thread
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
    """Everything stored about one map, or the part of it a loader was asked for.

    ``snapshot`` is the state the batches start from: the restart snapshot (or the base, when that is
    newer) for ``load_map`` and ``load_since``, the base for ``load_history``; None: the map's creation.
    """

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
    #: version -> the poses a correction gave that batch's scans (``logcodec.encode_poses``; opaque here): the batch
    #: replays at them (``logcodec.moved``)
    poses: dict[int, bytes] = field(default_factory=dict)


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
    base_version: int = 0  # the version the history starts after (its base snapshot's; 0: the map's creation)
    history_bytes: int = 0  # payload bytes of the history's batches (every one after the base)
    history_scans: int = 0  # scans in them
    from_stamp_ns: int | None = None  # the first stamp among them (None: no stamped scan)


class BatchRecord(NamedTuple):
    """One batch to append to the map ``name`` of that ``incarnation``; the store gives it its version."""

    name: str
    incarnation: str | None
    payload: bytes
    updated: str  # the map's new ``updated``
    scans: int
    stamp_ns: int | None = None  # its first stamped scan's stamp (Unix ns), if any: where a history starts


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

    def load_history(self, name: str, up_to: int | None = None, after: int | None = None) -> StoredMap | None:
        """The map's base snapshot (None: none yet, the history starts at the creation) and every batch after it,
        up to ``up_to`` (None: the newest); None when there is no map of that name. ``after``: only the batches
        after that version (and the base only when it is newer), whatever the restart snapshot."""

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
        """Store the map's state at ``version`` as its restart snapshot (the batches it covers stay: the history).

        A no-op when the stored restart snapshot (or the base) is as new or newer, or the map (of that
        incarnation) is gone.
        """

    def fold_point(self, name: str, keep_bytes: int) -> int:
        """The newest version to fold for the history after it to take at most ``keep_bytes`` (0: none to fold).

        Never above the restart snapshot's version (a restart replays the batches after it).
        """

    def write_base(self, name: str, version: int, payload: bytes | None, incarnation: str | None = None,
                   planned_at: int | None = None) -> bool:
        """Fold the history up to ``version``: store ``payload`` (the map at ``version``) as the base snapshot and
        drop the batches it covers, atomically; ``payload`` None: the restart snapshot, which must be at
        ``version``, becomes the base. Whether it was done: not when the base is as new or newer (another
        replica folded first), the restart snapshot is older than ``version``, or the map is gone.
        """

    def put_correction(self, name: str, incarnation: str | None, correction_id: str, through_version: int,
                       payload: bytes, requested: str, owner: str, lease_until: float) -> None:
        """Durably store a pending correction of the map (replacing its last one), held by ``owner`` until
        ``lease_until``; ``MapGone`` when the map is not stored under that incarnation (``app.storage.corrections``)."""

    def correction(self, name: str, *, with_payload: bool = False) -> StoredCorrection | None:
        """The map's latest correction, if any (its payload while pending, when asked)."""

    def correction_orphans(self, now: float) -> list[tuple[str, str]]:
        """(map, id) of the pending corrections whose owner's lease ran out before ``now``."""

    def claim_correction(self, name: str, correction_id: str, owner: str, lease_until: float, now: float) -> bool:
        """Take or keep the pending correction for ``owner``; whether it is ``owner``'s."""

    def report_correction(self, name: str, correction_id: str, owner: str, lease_until: float,
                          progress: dict[str, Any]) -> bool:
        """Renew the lease and store the progress; False when the correction is no longer ``owner``'s pending one."""

    def fail_correction(self, name: str, correction_id: str, progress: dict[str, Any]) -> None:
        """Mark the pending correction failed, its report saying why."""

    def switch_reposed(self, name: str, incarnation: str | None, change: Switch, snapshot: bytes) -> int | None:
        """Replace the map by its rebuild at the correction, in one transaction (``corrections.switch``): the new
        version, or None when a batch was stored after ``change.expect_version``. ``Superseded``, ``MapGone``."""

    def close(self) -> None:
        """Flush and release the store."""


#: What the loaders read first, in one query of either dialect (``?`` placeholders).
_LOAD_HEAD = ("SELECT meta, updated, version, snapshot_version, incarnation,"
             " (SELECT version FROM snapshots WHERE map = maps.name),"
             " (SELECT MAX(seq) FROM batches WHERE map = maps.name),"
             " base_version, (SELECT version FROM bases WHERE map = maps.name)"
             " FROM maps WHERE name = ?")
#: The versions of a map's restart snapshot and base rows (None: none), in either dialect.
START_ROWS = "SELECT (SELECT version FROM snapshots WHERE map = ?), (SELECT version FROM bases WHERE map = ?)"
#: A batch row's payload bytes (a row from before the ``bytes`` column: its inline payload's).
BATCH_BYTES = "COALESCE(bytes, length(payload))"
#: The history's bytes and scans as its rows hold them, for ``UPDATE maps SET (history_bytes, history_scans) =``.
HISTORY_OF_ROWS = (f"(SELECT COALESCE(SUM({BATCH_BYTES}), 0), COALESCE(SUM(scans), 0) FROM batches "
                   "WHERE batches.map = maps.name)")
#: Above every version: the bound of a range query that has none.
NO_LIMIT = 2**62


#: The first stamp of a map's history, as a column of the head queries (either dialect).
HISTORY_FROM_STAMP = "(SELECT first_stamp FROM batches WHERE map = maps.name AND first_stamp IS NOT NULL ORDER BY seq LIMIT 1)"


def head_of(row: Sequence[Any]) -> MapHead:
    """A ``MapHead`` from (name, meta, updated, version, snapshot_version, scans, incarnation, base_version,
    history_bytes, history_scans, ``HISTORY_FROM_STAMP``)."""
    return MapHead(row[0], json.loads(row[1]), row[2], int(row[3]), int(row[4]), int(row[5]), row[6],
                   int(row[7] or 0), int(row[8] or 0), int(row[9] or 0), None if row[10] is None else int(row[10]))


def start_of(snapshot_row: int | None, base_row: int | None, *, from_base: bool) -> tuple[int, str | None]:
    """Where a load starts: the version and table of the row it reads first (0 and None: the map's creation).

    A restart starts from the newer of the restart snapshot and the base (a fold may have made the
    restart snapshot the base); a history, from the base.
    """
    if base_row is not None and (from_base or snapshot_row is None or base_row > snapshot_row):
        return base_row, "bases"
    if snapshot_row is not None and not from_base:
        return snapshot_row, "snapshots"
    return 0, None


def may_fold(base_version: int, restart_version: int | None, version: int, *, moving: bool) -> bool:
    """Whether ``write_base`` may fold the history up to ``version``: not done already (by another replica), never
    past the restart snapshot (a restart replays the batches after it), and the restart snapshot made the base
    (``moving``) only at its own version."""
    return base_version < version <= (restart_version or 0) and (not moving or restart_version == version)


def fold_rows(execute: Callable[[str, tuple[Any, ...]], Any], name: str, version: int,
              base: tuple[str, tuple[Any, ...]] | None, columns: str) -> None:
    """``write_base``'s statements once it may fold, run by ``execute`` (``?`` placeholders) in its transaction: the
    base replaced by ``base`` (its INSERT and arguments; None: the restart snapshot's row, its ``columns``, moves),
    the batches it covers deleted, the history counted again."""
    execute("DELETE FROM bases WHERE map = ?", (name,))
    if base is None:
        execute(f"INSERT INTO bases ({columns}) SELECT {columns} FROM snapshots WHERE map = ?", (name,))
        execute("DELETE FROM snapshots WHERE map = ?", (name,))
    else:
        execute(*base)
    execute("DELETE FROM batches WHERE map = ? AND seq <= ?", (name, version))
    execute(f"UPDATE maps SET base_version = ?, (history_bytes, history_scans) = {HISTORY_OF_ROWS} WHERE name = ?",
            (version, name))


def fold_point_of(sizes: Iterable[Sequence[Any]], keep_bytes: int, restart_version: int) -> int:
    """``Storage.fold_point`` from the history's (version, bytes) rows, newest first."""
    kept = 0
    for seq, size in sizes:
        kept += int(size or 0)
        if kept > keep_bytes:
            return min(int(seq), restart_version)
    return 0


def read_map(query: Callable[[str, tuple[Any, ...]], Iterable[Sequence[Any]]], name: str, after: int | None,
             up_to: int | None, files: PayloadSource | None = None, *, from_base: bool = False) -> StoredMap | None:
    """``load_map`` (``after`` None), ``load_since`` or ``load_history`` (``from_base``) on a consistent view of a
    store: ``query(sql, args)`` runs one statement of either dialect (``?`` placeholders) and yields its rows.
    ``files``: where the store keeps its big payloads (rows with a ``file`` column), if it does."""
    file_column = "file" if files is not None else "NULL"
    row = next(iter(query(_LOAD_HEAD, (name,))), None)
    if row is None:
        return None
    meta, updated, version, snapshot_version, incarnation, snapshot_row, newest_seq, base_version, base_row = row
    start, table = start_of(snapshot_row, base_row, from_base=from_base)
    newest = max(snapshot_version or 0, snapshot_row or 0, base_row or 0, newest_seq or 0)
    stored = StoredMap(name, json.loads(meta), updated, snapshot_version=start,
                       incarnation=incarnation, version=newest if version is None else version)
    if table is not None and (after is None or start > after):
        what = "its base snapshot" if table == "bases" else "its snapshot"
        for snapshot in query(f"SELECT version, payload, crc, updated, {file_column} FROM {table} WHERE map = ?",
                              (name,)):
            payload = _payload(stored, f"{what} (version {snapshot[0]})", snapshot[1], snapshot[4], files)
            if payload is not None:
                _take_snapshot(stored, what, snapshot[0], payload, snapshot[2])
            if snapshot[3] is not None:
                stored.stamps[snapshot[0]] = snapshot[3]
    lower = start if after is None else max(after, start)
    # (a recorded snapshot or base whose row is gone is reported as such below, not again as the batches it held)
    recorded = (base_version or 0) if from_base else max(snapshot_version or 0, base_version or 0)
    previous = max(after or 0, start, recorded)
    for seq, stored_payload, crc, stamp, file, poses in query(
            f"SELECT seq, payload, crc, updated, {file_column}, poses FROM batches WHERE map = ? AND seq > ? "
            "AND seq <= ? ORDER BY seq", (name, lower, NO_LIMIT if up_to is None else up_to)):
        _check_gap(stored, previous, seq, stamp)
        previous = seq
        payload = _payload(stored, f"its stored batch {seq}", stored_payload, file, files)
        if payload is not None:
            _take_batch(stored, seq, payload, crc)
        if poses is not None:
            stored.poses[seq] = bytes(poses)
        if stamp is not None:
            stored.stamps[seq] = stamp
    if up_to is not None and previous < up_to:  # a gap just below up_to shows only in the row above it
        for seq, stamp in query("SELECT seq, updated FROM batches WHERE map = ? AND seq > ? ORDER BY seq LIMIT 1",
                                (name, previous)):
            _check_gap(stored, previous, seq, stamp)
    _check_versions(stored, version, snapshot_version, snapshot_row or 0, newest_seq or 0, base_version or 0,
                    base_row or 0)
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


def _take_snapshot(stored: StoredMap, what: str, version: int, payload: bytes, crc: int | None) -> None:
    if crc is not None and crc != checksum(payload):
        stored.damage.append(f"{what} (version {version}) fails its checksum")
    stored.snapshot_version, stored.snapshot = version, payload


def _take_batch(stored: StoredMap, seq: int, payload: bytes, crc: int | None) -> None:
    if crc is not None and crc != checksum(payload):
        stored.damage.append(f"its stored batch {seq} fails its checksum")
    elif payload == TOMBSTONE:
        return  # a discarded batch: nothing to replay (a damaged one is reported above, not skipped)
    stored.batches.append((seq, payload))


def _check_versions(stored: StoredMap, version: int | None, snapshot_version: int | None, snapshot_row: int,
                    newest_seq: int, base_version: int, base_row: int) -> None:
    """Rows deleted behind the service's back: the map's own record of its versions disagrees with its rows.

    (A deleted snapshot row left a map without batches 1-10 reporting version 12; a deleted last batch
    went unnoticed.) ``snapshot_row``/``newest_seq``: the stored snapshot's version and the newest
    batch row, tombstones included (0: none). NULL record: a database from before it, not checked
    until the next write. The restart snapshot's row may have become the base (a fold at its version).
    """
    if snapshot_version and snapshot_version not in (snapshot_row, base_row):
        stored.damage.append(f"its snapshot (version {snapshot_version}) is missing"
                             + (f"; version {snapshot_row} is stored" if snapshot_row else ""))
    if base_version and base_row != base_version:
        stored.damage.append(f"its base snapshot (version {base_version}) is missing")
    newest = max(snapshot_row, base_row, newest_seq)
    if version is not None and newest < version:
        stored.damage.append(f"its batches up to version {version} are missing (the newest stored is {newest})")
