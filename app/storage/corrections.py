"""A map's correction: a corrected trajectory's new poses, stored until the map is rebuilt at them, and the switch.

One row per map in ``corrections`` (the newest correction; a PUT replaces it): ``pending`` from the PUT's commit
until the rebuilt map is stored, then ``done`` (or ``failed``), its payload dropped and its ``report`` kept for
``GET /maps/{name}/rebuild``. A pending row is worked on by one replica at a time: ``owner`` holds it until
``lease_until`` (Unix seconds), renewed as it reports progress; a replica finding the lease run out takes it over
(the first owner was killed). The statements are shared by both stores (``?`` placeholders, run by an ``execute``
of either dialect), as ``fold_rows`` is.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from app.storage.base import HISTORY_OF_ROWS, MapGone, checksum

#: ``execute(sql, args)`` of either store with ``?`` placeholders, returning a cursor.
Execute = Callable[[str, tuple[Any, ...]], Any]

PENDING, DONE, FAILED = "pending", "done", "failed"

#: The table, in either dialect (``{blob}``, ``{int}`` and ``{real}`` filled in by the store).
SCHEMA = """CREATE TABLE IF NOT EXISTS corrections (
    map TEXT PRIMARY KEY REFERENCES maps(name) ON DELETE CASCADE,
    id TEXT NOT NULL,
    state TEXT NOT NULL,
    payload {blob},
    crc {int},
    through_version {int} NOT NULL,
    requested TEXT NOT NULL,
    owner TEXT,
    lease_until {real},
    version {int},
    report TEXT NOT NULL
)"""


class Superseded(Exception):
    """The correction is no longer the map's pending one (a newer PUT replaced it, or the map was deleted)."""


@dataclass(frozen=True)
class StoredCorrection:
    """A map's correction row: ``payload`` the poses to give (``app.maps.correction``), None once finished."""

    name: str
    id: str
    state: str
    through_version: int
    requested: str
    owner: str | None
    lease_until: float | None
    version: int | None
    report: dict[str, Any]
    payload: bytes | None = None
    damage: str | None = None


@dataclass(frozen=True)
class Switch:
    """What replaces a map by its rebuild, in one transaction (``switch``).

    ``expect_version``: the stored version the rebuilt map has caught up to (the switch is refused, None, when
    another batch was stored since); ``poses``: (version, ``logcodec.encode_poses`` bytes) of each batch whose scans
    moved; ``marker``: the ``Reposed`` record, stored as the next version; ``snapshot``: the rebuilt map at that
    version, as its restart snapshot (SQL and arguments of the store's insert, ``{version}`` in them filled here).
    """

    id: str
    expect_version: int
    base_version: int
    poses: Sequence[tuple[int, bytes]]
    marker: bytes
    updated: str
    report: dict[str, Any] = field(default_factory=dict)


def put(execute: Execute, name: str, incarnation: str | None, correction_id: str, through_version: int,
        payload: bytes, requested: str, owner: str, lease_until: float) -> None:
    """Store a pending correction of map ``name`` (replacing the one before, pending or not), held by ``owner``;
    ``MapGone`` when the map is not stored under that incarnation."""
    if execute("SELECT 1 FROM maps WHERE name = ? AND (CAST(? AS TEXT) IS NULL OR incarnation = ?)",
               (name, incarnation, incarnation)).fetchone() is None:
        raise MapGone(name)
    execute("DELETE FROM corrections WHERE map = ?", (name,))
    execute("INSERT INTO corrections (map, id, state, payload, crc, through_version, requested, owner, lease_until, "
            "report) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (name, correction_id, PENDING, payload, checksum(payload), through_version, requested, owner, lease_until,
             "{}"))


_COLUMNS = "map, id, state, through_version, requested, owner, lease_until, version, report"


def _row(row: Sequence[Any], payload: bytes | None = None, crc: int | None = None) -> StoredCorrection:
    damage = None
    if payload is not None and crc is not None and checksum(bytes(payload)) != crc:
        damage = "the stored correction fails its checksum"
    return StoredCorrection(row[0], row[1], row[2], int(row[3]), row[4], row[5],
                            None if row[6] is None else float(row[6]), None if row[7] is None else int(row[7]),
                            json.loads(row[8]), None if payload is None else bytes(payload), damage)


def read(execute: Execute, name: str, *, with_payload: bool = False) -> StoredCorrection | None:
    """The map's correction row (its payload too, when asked and pending); None when it has none."""
    row = execute(f"SELECT {_COLUMNS}, payload, crc FROM corrections WHERE map = ?" if with_payload
                  else f"SELECT {_COLUMNS}, NULL, NULL FROM corrections WHERE map = ?", (name,)).fetchone()
    return None if row is None else _row(row[:9], row[9], row[10])


def orphans(execute: Execute, now: float) -> list[tuple[str, str]]:
    """(map, id) of the pending corrections whose owner's lease has run out (it was killed, or stopped)."""
    return [(str(m), str(i)) for m, i in execute(
        "SELECT map, id FROM corrections WHERE state = ? AND (lease_until IS NULL OR lease_until < ?) ORDER BY map",
        (PENDING, now)).fetchall()]


def claim(execute: Execute, name: str, correction_id: str, owner: str, lease_until: float, now: float) -> bool:
    """Take (or keep) the pending correction ``correction_id`` for ``owner`` until ``lease_until``: when it is still the
    map's pending one and held by ``owner`` or by nobody alive. Whether it is ``owner``'s now."""
    return execute("UPDATE corrections SET owner = ?, lease_until = ? WHERE map = ? AND id = ? AND state = ? "
                   "AND (owner = ? OR lease_until IS NULL OR lease_until < ?) RETURNING 1",
                   (owner, lease_until, name, correction_id, PENDING, owner, now)).fetchone() is not None


def report(execute: Execute, name: str, correction_id: str, owner: str, lease_until: float,
           progress: dict[str, Any]) -> bool:
    """Renew ``owner``'s lease and store the rebuild's progress; False when the correction is no longer ``owner``'s
    pending one (superseded, taken over, the map deleted): the rebuild stops."""
    return execute("UPDATE corrections SET lease_until = ?, report = ? WHERE map = ? AND id = ? AND state = ? "
                   "AND owner = ? RETURNING 1",
                   (lease_until, json.dumps(progress), name, correction_id, PENDING, owner)).fetchone() is not None


def fail(execute: Execute, name: str, correction_id: str, progress: dict[str, Any]) -> None:
    """Mark the pending correction ``correction_id`` failed (its report says why); nothing when it is not pending."""
    execute("UPDATE corrections SET state = ?, payload = NULL, crc = NULL, owner = NULL, lease_until = NULL, "
            "report = ? WHERE map = ? AND id = ? AND state = ?",
            (FAILED, json.dumps(progress), name, correction_id, PENDING))


def blocks_fold(execute: Execute, name: str, planned_at: int | None) -> bool:
    """Whether a fold planned from the history at version ``planned_at`` must not be stored: a correction is pending
    (its batches must stay re-posable until it is applied), or a switch since then moved the history's poses (the
    fold's base was fused at the old ones)."""
    row = execute("SELECT state, version FROM corrections WHERE map = ?", (name,)).fetchone()
    if row is None:
        return False
    return row[0] == PENDING or (planned_at is not None and row[1] is not None and int(row[1]) > planned_at)


def switch(execute: Execute, name: str, version: int, base_version: int, change: Switch,
           snapshot: Callable[[int], None]) -> int | None:
    """The rebuilt map replaces the map in the store: the moved batches take their new poses, the ``Reposed`` record
    is appended as the next version, ``snapshot(version)`` stores the rebuilt map as the restart snapshot at it, and
    the correction is done. ``version`` and ``base_version``: the map's, read by the store under its row lock.

    The new version; None when a batch was stored since the rebuild caught up (``expect_version``: catch up and try
    again). ``Superseded`` when the correction is no longer the map's pending one or the history was folded.
    """
    row = execute("SELECT id, state FROM corrections WHERE map = ?", (name,)).fetchone()
    if row is None or row[0] != change.id or row[1] != PENDING:
        raise Superseded(name)
    if base_version != change.base_version:
        raise Superseded(name)  # cannot happen while it is pending (folds wait): the rebuild started from another base
    if version != change.expect_version:
        return None
    for seq, poses in change.poses:
        execute("UPDATE batches SET poses = ? WHERE map = ? AND seq = ?", (poses, name, seq))
    new = version + 1
    execute("INSERT INTO batches (map, seq, payload, crc, scans, updated, bytes) VALUES (?, ?, ?, ?, 0, ?, ?)",
            (name, new, change.marker, checksum(change.marker), change.updated, len(change.marker)))
    execute(f"UPDATE maps SET version = ?, updated = ?, (history_bytes, history_scans) = {HISTORY_OF_ROWS} "
            "WHERE name = ?", (new, change.updated, name))
    snapshot(new)
    execute("UPDATE corrections SET state = ?, payload = NULL, crc = NULL, owner = NULL, lease_until = NULL, "
            "version = ?, report = ? WHERE map = ?", (DONE, new, json.dumps({**change.report, "version": new}), name))
    return new
