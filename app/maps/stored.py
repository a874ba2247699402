"""A map from what is stored of it: its metadata, its snapshot's arrays (``snapshotcodec``), its log replayed.

``restore`` rebuilds a held map from its snapshot and the batches after it, in order; fusion is
deterministic, so the map is bit for bit the one acknowledged. ``build_map`` is a new map too: what is
stored is what runs.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from app.maps import logcodec, snapshotcodec
from app.maps.entry import UNLIMITED_CELLS, MapEntry, OccupancyMap, spec_of
from app.maps.logcodec import Batch, Clear, Prior, Reposed, SetForget
from app.scans import Scan
from app.schemas import engine_choice
from app.storage import StoredMap
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LatticeSpec, IntegrationStats, SensorModel, cast_work
from fuzzyocc.castahead import CastAhead
from fuzzyocc.maps import PRIOR_UNSEEN, PreparedBatch

LOG = logging.getLogger("fuzzyrisk.maps")


def build_map(meta: Mapping[str, Any], *, max_cells: int) -> OccupancyMap:
    """An empty map as ``meta`` describes it (a new map is built from its meta too: what is stored is what runs)."""
    spec = spec_of(meta, max_cells=max_cells)
    sensor = SensorModel(**meta["sensor"])
    if meta["model"] == "fuzzy":
        built = FuzzyMap(spec, sensor, engine_choice.from_meta(meta))
        built.forget_beyond = meta.get("forget_beyond")
        return built
    return BayesMap(cast(GridSpec, spec), sensor)


def integrate(built: OccupancyMap, batch: Batch, prepared: PreparedBatch | None = None) -> IntegrationStats:
    """Fuse a batch of the log into ``built``: its scans (cast ahead as ``prepared``, if given), its prior, or its
    edit (the cells a clear set back to never observed count as updated)."""
    if isinstance(batch, Prior):
        return built.integrate_prior(batch.levels)
    if isinstance(batch, Clear):
        return IntegrationStats(scans=0, rays=0, cells_updated=built.clear(batch.low, batch.high))
    if isinstance(batch, SetForget):
        built.forget_beyond = batch.metres
        return IntegrationStats(scans=0, rays=0, cells_updated=0)
    if isinstance(batch, Reposed):  # the batches before it were replayed at their new poses
        return IntegrationStats(scans=0, rays=0, cells_updated=0)
    return built.integrate_batch(batch, prepared)


def batch_work(spec: GridSpec | LatticeSpec, batch: Batch) -> int:
    """The cells fusing ``batch`` walks (``cast_work`` of scans; a prior's cells, once a scan it stands for)."""
    if isinstance(batch, Prior):
        return int(np.abs(batch.levels[batch.levels != PRIOR_UNSEEN].astype(np.int64)).sum())
    if isinstance(batch, (Clear, SetForget, Reposed)):
        return 0  # a clear walks the map's blocks once, not rays
    return cast_work(spec, batch)


def restore(stored: StoredMap, up_to: int | None = None, progress: Callable[[int], None] | None = None) -> MapEntry:
    """A map from its snapshot and the batches after it (replayed in order: bit-identical risk).

    ``up_to``: replay only the batches up to that version (a live map's rebuild: later batches
    may be committed and still waiting for their turn to be applied). ``progress``: called with the
    scans of each batch once it is fused (an exception it raises stops the replay).
    """
    if stored.damage:
        raise RuntimeError(f"map {stored.name!r}: {'; '.join(stored.damage)}")
    try:
        built = build_map(stored.meta, max_cells=UNLIMITED_CELLS)
    except ValueError as exc:
        raise RuntimeError(f"map {stored.name!r}: its stored metadata cannot be used ({exc}); the database "
                           "needs repair") from exc
    if stored.snapshot is not None:
        arrays = snapshotcodec.decode(stored.snapshot)
        if isinstance(built, FuzzyMap):
            # the snapshot holds forget_beyond as it was at its version (a PATCH logged before it is not replayed)
            built = FuzzyMap.from_arrays(built.spec, built.sensor, arrays, built.engine)
        else:
            built = BayesMap.from_arrays(built.spec, built.sensor, arrays)
    entry = MapEntry(
        dict(stored.meta), built, stored.snapshot_version, stored.snapshot_version, built.scans_fused,
        stored.stamps.get(stored.snapshot_version, stored.updated),
    )
    done = replay(entry.map, stored, after=entry.version, up_to=up_to, progress=progress)
    entry.version, entry.scans_fused, entry.updated = done.version or entry.version, built.scans_fused, \
        done.updated or entry.updated
    entry.last_scan = done.last_scan
    entry.log.extend(done.log)
    # versions up to the stored one that were not replayed are discarded batches (tombstones)
    entry.checked = stored.version if up_to is None else min(stored.version, up_to)
    return entry


@dataclass
class Replayed:
    """What ``replay`` brought a map to: its newest version replayed (0: none), that batch's ``updated``, ..."""

    version: int = 0
    updated: str = ""
    last_scan: Scan | None = None
    #: (version, bytes, cells walked) of the batches replayed, for ``MapEntry.log``
    log: list[tuple[int, int, int]] = field(default_factory=list)


def replay(built: OccupancyMap, stored: StoredMap, *, after: int, up_to: int | None = None,
           progress: Callable[[int], None] | None = None) -> Replayed:
    """Fuse ``stored``'s batches above version ``after`` (and at most ``up_to``) into ``built``, in order, each at the
    poses a correction gave it (``stored.poses``); ``progress`` as ``restore``'s. A batch of scans followed by
    another is fused while the next one is cast (``CastAhead``: the same map, sooner)."""
    replayed = Replayed()
    batches = _decoded(stored, after, up_to)
    current = next(batches, None)
    with CastAhead(built) as ahead:
        while current is not None:
            following = next(batches, None)
            version, size, batch = current
            try:
                if isinstance(batch, list):
                    stats = ahead.integrate(batch, following[2] if following and isinstance(following[2], list)
                                            else None)
                else:
                    stats = integrate(built, batch)
            except ValueError:
                # cannot happen for a batch that was acknowledged (it was applied before the 200)
                LOG.exception("map %s: batch %d cannot be replayed; skipped", stored.name, version)
                replayed.log.append((version, size, 0))
                current = following
                continue
            # scans: the cells their cast walked, as the fusion counts them (``cast_work`` made and walked every
            # scan's rays a second time, 3-6 % of a replay, for a figure a rebuild then discards)
            walked = stats.cells_traversed if isinstance(batch, list) else batch_work(built.spec, batch)
            replayed.log.append((version, size, walked))
            replayed.version = version
            if isinstance(batch, list) and batch:  # a prior or an edit fuses no scan
                replayed.last_scan = batch[-1]
            replayed.updated = stored.stamps.get(version, stored.updated)
            if progress is not None:
                progress(len(batch) if isinstance(batch, list) else 0)
            current = following
    return replayed


def _decoded(stored: StoredMap, after: int, up_to: int | None) -> Iterator[tuple[int, int, Batch]]:
    """``stored``'s batches above ``after`` (at most ``up_to``) decoded, at their corrected poses: (version, its
    stored bytes, the batch)."""
    for version, payload in stored.batches:
        if version <= after:
            continue
        if up_to is not None and version > up_to:
            return
        try:
            if version in stored.poses:  # moved by a correction: replayed at its new poses
                payload = logcodec.with_poses(payload, stored.poses[version])
            batch = logcodec.decode(payload)
        except logcodec.CorruptBatch as exc:
            # an acknowledged batch: never dropped silently; the service refuses to start and says where
            raise RuntimeError(f"map {stored.name!r}: stored batch {version} is corrupt ({exc}); the database "
                               f"needs repair (restore a backup, or delete that row to drop the batch)") from exc
        yield version, len(payload), batch
