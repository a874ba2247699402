"""A map's history: rebuilt from its base and every batch after it, and its oldest batches folded into the base.

The history is every batch stored after the base snapshot (scans, priors, edits, tombstones), in
order; while no batch has left it there is no base and it starts at the map's creation. ``rebuild``
fuses it all again: the map a rebuild after a loop closure starts from. ``plan_fold`` picks the
oldest batches to leave it when it takes more than ``FUZZYRISK_MAX_HISTORY_BYTES``, and makes the
map at their last version (the base they fold into); ``Storage.write_base`` stores it and drops
them in one transaction.
"""

from __future__ import annotations

from dataclasses import dataclass

from app.maps.entry import MapEntry
from app.maps import snapshotcodec
from app.maps.stored import restore
from app.storage import Storage, StoredMap
from app.storage.corrections import PENDING

#: A fold keeps the newest history up to this share of the budget, so that folds are rare (each
#: re-fuses the batches it folds).
FOLD_DOWN_TO = 0.75


def rebuild(history: StoredMap, up_to: int | None = None) -> MapEntry:
    """The map from its base (or its creation) and its history's batches up to ``up_to`` (None: every one), fused
    in order as a restart fuses them: bit for bit the map fused from the history's start (``Storage.load_history``
    gives ``history``)."""
    return restore(history, up_to)


@dataclass(frozen=True)
class Fold:
    """The history up to ``version`` folded into a base: ``payload`` the map at ``version`` (None: the restart
    snapshot, which is at ``version``), planned from the map at ``planned_at`` (a correction's switch since then moved
    the history's poses: ``Storage.write_base`` then refuses it)."""

    version: int
    payload: bytes | None
    planned_at: int


def plan_fold(storage: Storage, name: str, incarnation: str | None, *, budget: int, replay: bool) -> Fold | None:
    """The fold that brings the map's history under ``budget`` bytes (to about ``FOLD_DOWN_TO`` of it), or None:
    under the budget, nothing foldable (every batch over it is after the restart snapshot), the map gone, or
    ``replay`` False and the fold would need the history re-fused (it is not at the restart snapshot).

    Blocking and CPU-heavy (the history up to the fold re-fused): run it in a thread.
    """
    head = storage.map_head(name)
    if head is None or head.incarnation != incarnation or head.history_bytes <= budget:
        return None
    pending = storage.correction(name)
    if pending is not None and pending.state == PENDING:
        return None  # its batches stay re-posable until the correction is applied (``write_base`` checks it too)
    version = storage.fold_point(name, int(budget * FOLD_DOWN_TO))
    if version <= head.base_version:
        return None
    if version == head.snapshot_version:
        return Fold(version, None, head.version)  # the restart snapshot is that map: nothing to fuse
    if not replay:
        return None
    history = storage.load_history(name, up_to=version)
    if history is None or history.incarnation != incarnation:
        return None
    return Fold(version, snapshotcodec.encode(rebuild(history, up_to=version).map.snapshot_arrays()), head.version)
