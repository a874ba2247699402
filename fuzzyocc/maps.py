"""Occupancy maps: scans in, fused cell states, defuzzified risk out.

:class:`FuzzyMap` (Payeur's fuzzy fusion) and :class:`BayesMap` (closed-form OPDF merged by
Bayes in log-odds, clamped like OctoMap) share the orchestration in :class:`OccupancyMap`:

1. validate every scan of a batch (nothing is touched if one is bad);
2. cast all beams of the batch (:func:`fuzzyocc.raycast.cast_rays`): per scan, each cell
   reached once, with the evidence of its most occupied-ward beam, so grazing beams do not
   erase thin obstacles (OctoMap's "occupied before free");
3. scan by scan, in order: mark the reached cells observed and update the cells whose
   evidence is not pure UNK (that column of Table 1 is the identity) -- the only step
   where the two models differ.

Beam geometry: a hit at range ``r`` updates the cells from the sensor to
``r + occupied_extent * sigma`` (the end of the occupied region behind the surface); a
no-return updates the cells up to ``range_max`` as free space. ``sigma`` of a beam is
``sensor.sigma(r, scan.registration_sigma)``, divided by ``max(sin(incidence),
incidence_floor)`` for a FuzzyMap whose engine sets one (LaserScan beams only), floored at
half a cell. A FuzzyMap whose engine sets ``no_return_neighbours`` cuts a LaserScan's
no-returns that have hits beside them (:meth:`fuzzyocc.scans.Rays.cut_no_returns`).

Maps are not thread-safe: serialise calls on one map.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from fuzzyocc import bayes, presets
from fuzzyocc.config import MAX_COORDINATE_M, GridSpec, LatticeSpec, SensorModel
from fuzzyocc.engine import FuzzyEngine
from fuzzyocc._block_table import BlockIndex
from fuzzyocc.blockgrid import BLOCK_SHIFT_2D, BLOCK_SHIFT_3D, BlockGrid, block_shift_for
from fuzzyocc.grid import CellGrid
from fuzzyocc.keys import coords_to_keys, keys_to_flat
from fuzzyocc.raycast import (
    CastResult,
    Lattice,
    cast_into,
    cross_into,
    enter_new_blocks,
    fits,
    flat_ids,
    give_back,
    traversal_cells,
)
from fuzzyocc.scans import LaserScan, PointCloud, Rays

Scan = LaserScan | PointCloud

_BAYES_CHUNK = 1 << 16  # cells per step of a Bayes update (each cell is updated on its own)
#: (scan, cell) entries one cast of a batch may hold (12 bytes each: about 200 MB); see ``_cast_chunks``
CAST_CHUNK_ENTRIES = 16_000_000
#: beams one cast may hold (about 300 bytes each while their rays are made and cast: about 40 MB); a scan with
#: more is cast part by part (see ``_cast_in_parts``). A 128-beam lidar's sweep (131,072 beams) is one cast: cast
#: in two parts, the Ouster frames spent more time merging the parts' cells than casting them.
CAST_CHUNK_BEAMS = 131_072
#: The evidence of one agreeing scan in a prior (``OccupancyMap.integrate_prior``), in sigmas from the measured
#: surface (eq. 5): an occupied cell's is that of the cell a beam ends in, the surface at its centre; a free
#: cell's that of a cell a beam crosses far in front of its surface (3 m at the default 0.03 m), where every
#: preset's input functions are flat and the Bayes OPDF has reached its front plateau.
PRIOR_HIT_SIGMAS = 0.0
PRIOR_PASS_SIGMAS = -100.0
#: The prior level of a cell no scan reached: ``integrate_prior`` leaves it as it is.
PRIOR_UNSEEN = -128
#: Most agreeing scans one prior cell may stand for: every engine here saturates well before (``evidence`` after
#: 3 hits or 5 pass-throughs, Bayes at its clamps after 12 hits), and each is one more pass over the cells.
MAX_PRIOR_SCANS = 20


def scan_parts(scan: Scan) -> list[slice]:
    """``scan``'s readings in consecutive slices of at most ``CAST_CHUNK_BEAMS`` (one empty slice for no reading):
    the pieces a huge scan is made into rays by, in bounded memory."""
    n = scan.beam_count
    return [slice(a, min(a + CAST_CHUNK_BEAMS, n)) for a in range(0, n, CAST_CHUNK_BEAMS)] or [slice(0, 0)]


def _defuzzified(engine: FuzzyEngine, state: np.ndarray) -> np.ndarray:
    return np.asarray(engine.defuzzify(state), dtype=np.float32)


def _probability(logodds: np.ndarray) -> np.ndarray:
    return np.asarray(bayes.probability(logodds), dtype=np.float32)


def cast_work(spec: GridSpec | LatticeSpec, scans: Sequence[Scan]) -> int:
    """About how many cells fusing ``scans`` into a map of ``spec`` walks (see ``traversal_cells``).

    What a batch costs in time is close to proportional to it (about 10 M cells a second per
    fusion thread on a 2-core EPYC), and it is known before any work: a service can
    refuse a batch that would hold a fusion thread for minutes.
    """
    total = 0
    for scan in scans:
        for part in scan_parts(scan):  # part by part: a scan of millions of beams is estimated in bounded memory
            rays = scan.to_rays(beams=part)
            total += traversal_cells(spec, rays.origin, rays.endpoints)
    return total


def allocation_bound(spec: GridSpec | LatticeSpec, scans: Sequence[Scan]) -> int:
    """At most about how many cells fusing ``scans`` makes a fuzzy map of ``spec`` hold anew: the cells of every
    block their beams reach, as if none were held yet.

    Counted by casting the beams over the lattice of blocks (one cell a block): a few times less work
    than the fusion, and known before it. A beam's occupied band behind its hit (a few sigmas) is not
    counted, nor are blocks the map already holds: a bound for refusing a batch that would take a
    map's memory at once (a cloud of kilometre-long beams), not a forecast.
    """
    ndim = spec.ndim
    side = 1 << (BLOCK_SHIFT_3D if ndim == 3 else BLOCK_SHIFT_2D)
    if isinstance(spec, GridSpec):
        lattice = Lattice(tuple(float(v) for v in spec.origin), spec.resolution * side,
                          tuple(-(-n // side) for n in spec.shape))
    else:
        lattice = Lattice((0.0,) * ndim, spec.resolution * side, None)
    index = BlockIndex()
    for scan in scans:
        for part in scan_parts(scan):
            rays = scan.to_rays(beams=part)
            n = rays.ranges.size
            if n:
                cross_into(lattice, index, np.repeat(rays.origin[None], n, axis=0), rays.directions, rays.ranges)
    return index.n * side**ndim


def _check_weight(weight: object) -> None:
    if not isinstance(weight, int) or isinstance(weight, bool) or not 1 <= weight <= MAX_PRIOR_SCANS:
        raise ValueError(f"weight must be a whole number of scans from 1 to {MAX_PRIOR_SCANS}, got {weight!r}")


def _check_spec(spec: object) -> None:
    if not isinstance(spec, (GridSpec, LatticeSpec)):
        raise ValueError(f"spec must be a GridSpec (a fixed box) or a LatticeSpec (a growing map), got "
                         f"{type(spec).__name__}")


@dataclass(frozen=True)
class Window:
    """A box of a map's cells: ``[lo, hi)`` lattice indices along x, y[, z].

    ``origin`` is the corner of its first cell in the map frame and ``shape`` its cells, as a
    grid answer states them (a Nav2 map YAML's ``origin``, an OccupancyGrid's ``info``)."""

    lo: tuple[int, ...]
    hi: tuple[int, ...]
    resolution: float
    lower: tuple[float, ...]

    @property
    def shape(self) -> tuple[int, ...]:
        """Cells along each axis."""
        return tuple(h - lo for lo, h in zip(self.lo, self.hi))

    def cells(self) -> int:
        """Cells in the window."""
        return math.prod(self.shape)

    @property
    def origin(self) -> tuple[float, ...]:
        """Corner of the first cell, metres."""
        return tuple(b + i * self.resolution for b, i in zip(self.lower, self.lo))

    @property
    def upper(self) -> tuple[float, ...]:
        """Far corner of the last cell, metres."""
        return tuple(b + i * self.resolution for b, i in zip(self.lower, self.hi))

    def spec(self) -> GridSpec:
        """The window as a fixed box (for a planner or an export), its corner as a person writes it (-1.3, not the
        -1.2999999999999998 of -5.0 + 37 * 0.1: 15 significant digits keep any coordinate within 1e7 m to 10 nm)."""
        return GridSpec(origin=tuple(float(f"{v:.15g}") for v in self.origin), size=tuple(n * self.resolution for n in self.shape),
                        resolution=self.resolution, max_cells=2 * math.prod(self.shape) + 16)


@dataclass(frozen=True)
class PreparedBatch:
    """A batch's cast made ahead of its fusion (:meth:`OccupancyMap.prepare_batch`)."""

    scans: tuple[Scan, ...]
    index: BlockIndex  # the index it was made on
    cast: CastResult
    beams: int
    skipped: int

    def of(self, scans: Sequence[Scan]) -> bool:
        """Whether this is the cast of ``scans`` (the very scans, in order)."""
        return len(self.scans) == len(scans) and all(a is b for a, b in zip(self.scans, scans))


@dataclass(frozen=True)
class IntegrationStats:
    """What one integrate call did.

    Attributes
    ----------
    scans : int
        Scans fused.
    rays : int
        Beams cast (hits and no-returns).
    cells_updated : int
        Cells given evidence (reached closer than ``occupied_extent`` sigmas behind a surface),
        summed over scans: a cell two scans reach counts twice.
    cells_traversed : int
        Cell visits of the ray casting, before the per-scan dedupe.
    rays_skipped : int
        Beams dropped as invalid (REP 117 ``-inf``/NaN/below ``range_min``, points at the origin).
    """

    scans: int
    rays: int
    cells_updated: int
    cells_traversed: int = 0
    rays_skipped: int = 0


class OccupancyMap:
    """Orchestration shared by the map models; subclasses give the per-cell update and risk."""

    model: str = ""

    def __init__(self, spec: GridSpec | LatticeSpec, sensor: SensorModel | None = None) -> None:
        _check_spec(spec)
        sensor = SensorModel() if sensor is None else sensor
        if not isinstance(sensor, SensorModel):
            raise ValueError(f"sensor must be a SensorModel, got {type(sensor).__name__}")
        self.spec = spec
        self.sensor = sensor
        self.lattice = (Lattice.of(spec) if isinstance(spec, GridSpec)
                        else Lattice((0.0,) * spec.ndim, spec.resolution, None))
        self._forget_beyond: float | None = None
        self._grid: CellGrid | BlockGrid = self._new_grid()
        self._scans_fused = 0

    @property
    def growing(self) -> bool:
        """Whether the map has no fixed box (its ``spec`` is a :class:`~fuzzyocc.config.LatticeSpec`)."""
        return isinstance(self.spec, LatticeSpec)

    @property
    def forget_beyond(self) -> float | None:
        """Metres: after each scan, cells whose centre lies farther than this from the scan's sensor (in the
        plane on a 2-D map) go back to never observed. None keeps everything."""
        return self._forget_beyond

    @forget_beyond.setter
    def forget_beyond(self, metres: float | None) -> None:
        if metres is not None:
            metres = float(metres)
            if not math.isfinite(metres) or metres <= 0.0:
                raise ValueError(f"forget_beyond must be a positive number of metres or None, got {metres!r}")
        self._forget_beyond = metres

    def _restore(self, state: np.ndarray, observed: np.ndarray, scans_fused: int) -> None:
        self._grid = self._grid_from(state, observed)
        self._scans_fused = scans_fused

    def _new_grid(self) -> CellGrid | BlockGrid:
        """Storage of a new map (every cell unknown, none observed)."""
        return self._grid_from(self._initial_state(), np.zeros(self.spec.num_cells, dtype=np.bool_))

    def _grid_from(self, state: np.ndarray, observed: np.ndarray) -> CellGrid | BlockGrid:
        """Storage holding ``state`` ((num_cells, ...), taken over) and ``observed``."""
        return CellGrid(self.spec, state, observed, self._risk_fn())

    # -- what a model defines ------------------------------------------------------------
    def _initial_state(self) -> np.ndarray:
        """(num_cells, ...) state of a new map (all unknown)."""
        raise NotImplementedError

    @property
    def occupied_extent(self) -> float:
        """Sigmas behind the surface past which a beam's evidence is pure UNK; its rays stop there."""
        raise NotImplementedError

    def _update(self, cells: np.ndarray, distance_sigmas: np.ndarray) -> int:
        """Fuse one scan's evidence (finite float32 distances, sigmas) into ``cells``; returns how many."""
        raise NotImplementedError

    def _update_scan(self, cells: np.ndarray, distance_sigmas: np.ndarray) -> int:
        """Fuse a scan's cast (``UNKNOWN_ONLY``, -inf: reached only past the occupied region, no update); how many
        cells took evidence."""
        evidence = np.isfinite(distance_sigmas)
        return self._update(cells[evidence], distance_sigmas[evidence])

    def _risk_fn(self) -> Callable[[np.ndarray], np.ndarray]:
        """(n, ...) states -> (n,) float32 risk, as a function that does not hold the map.

        (A bound method held by the map's own storage made every map a reference cycle: a
        map let go was freed only by the cyclic garbage collector, whenever it ran, so the
        memory of a deleted map could not go back to the system at the delete.)
        """
        raise NotImplementedError

    # -- integration ---------------------------------------------------------------------
    @property
    def scans_fused(self) -> int:
        """Scans fused since the map was created."""
        return self._scans_fused

    def integrate_scan(self, *, pose: Sequence[float], angle_min: float, angle_increment: float,
                       ranges: object, range_min: float, range_max: float,
                       registration_sigma: float = 0.0) -> IntegrationStats:
        """Fuse one planar scan (2-D maps only); see :class:`fuzzyocc.scans.LaserScan`."""
        scan = LaserScan(pose=pose, angle_min=angle_min, angle_increment=angle_increment,  # type: ignore[arg-type]
                         ranges=ranges, range_min=range_min, range_max=range_max,  # type: ignore[arg-type]
                         registration_sigma=registration_sigma)
        return self.integrate_batch([scan])

    def integrate_points(self, points: object, *, origin: Sequence[float], range_max: float,
                         registration_sigma: float = 0.0) -> IntegrationStats:
        """Fuse one point cloud given in the map frame; see :class:`fuzzyocc.scans.PointCloud`."""
        cloud = PointCloud(points=points, origin=tuple(origin), range_max=range_max,  # type: ignore[arg-type]
                           registration_sigma=registration_sigma)
        return self.integrate_batch([cloud])

    def prepare_batch(self, scans: Sequence[Scan]) -> PreparedBatch | None:
        """The cast of ``scans`` made now, leaving the map as it is, for :meth:`integrate_batch` to fuse: a caller
        that keeps readers off the map while it changes (a service's lock) casts before it shuts them out, and
        they wait for the fusion alone. None for a batch cast in several chunks or parts (cast as it is fused).

        Every scan is checked as :meth:`integrate_batch` checks it (``ValueError`` naming ``scans[i]``). The cast
        holds while the map's blocks stay as they are; :meth:`integrate_batch` casts again when they changed.
        """
        scans = self._checked(scans)
        if not scans or len(self._cast_chunks(scans)) != 1 or scans[0].beam_count > CAST_CHUNK_BEAMS:
            return None
        index, _ = self._cast_blocks()
        return PreparedBatch(tuple(scans), index, *self._cast_chunk(scans, enter=False))

    def chunked(self, scans: Sequence[Scan]) -> list[list[Scan]]:
        """``scans`` checked as :meth:`integrate_batch` checks them (``ValueError`` naming ``scans[i]``) and split
        as it casts them: the runs, each fused as a batch of its own in turn, make the map the whole batch makes."""
        scans = self._checked(scans)
        return [scans[first:last] for first, last in self._cast_chunks(scans)] if scans else []

    def enter_prepared(self, prepared: PreparedBatch) -> PreparedBatch | None:
        """Enter the blocks ``prepared``'s cast reached into the map now, ahead of its fusion; what
        :meth:`integrate_batch` of its scans then takes. From here to the end of that fusion the map's blocks stay
        as they are (unless the map forgets, ``forget_beyond``): another batch can be cast beside it
        (:class:`~fuzzyocc.castahead.CastAhead`). None, and nothing entered, if the blocks changed since the cast."""
        index, _ = self._cast_blocks()
        if prepared.index is not index or not fits(index, prepared.cast):
            return None
        enter_new_blocks(index, prepared.cast)
        self._cast_done()
        return dataclasses.replace(prepared, cast=dataclasses.replace(prepared.cast, new_blocks=None,
                                                                       index_at=(index.n, index.dropped)))

    def integrate_batch(self, scans: Sequence[Scan], prepared: PreparedBatch | None = None) -> IntegrationStats:
        """Fuse scans in order, all or none.

        Every scan is checked against the map first; if one is unusable, ``ValueError``
        (naming ``scans[i]``) is raised and the map is left exactly as it was. ``prepared``: their cast from
        :meth:`prepare_batch` (``ValueError`` if it is another batch's), used if the map's blocks have not changed
        since; the map is the same either way.
        """
        scans = self._checked(scans)
        if not scans:
            return IntegrationStats(scans=0, rays=0, cells_updated=0)
        if prepared is not None and not prepared.of(scans):
            raise ValueError("prepared is the cast of other scans")
        if prepared is not None:  # None if the blocks changed since (another batch, a clear): its slots name others
            prepared = self.enter_prepared(prepared)
        chunks = self._cast_chunks(scans)
        updated = traversed = n_rays = skipped = 0
        for first, last in chunks:
            if scans[first].beam_count > CAST_CHUNK_BEAMS:  # a chunk of its own (``_cast_chunks``)
                cast, beams, dropped = self._cast_in_parts(scans[first])
            elif prepared is not None:  # the batch's one chunk, its blocks entered
                cast, beams, dropped = prepared.cast, prepared.beams, prepared.skipped
                prepared = None
            else:
                cast, beams, dropped = self._cast_chunk(scans[first:last])
            n_rays, skipped = n_rays + beams, skipped + dropped
            traversed += int(cast.cells_traversed.sum())
            for s in range(last - first):
                lo, hi = cast.scan_offsets[s], cast.scan_offsets[s + 1]
                cells = self._stored_cells(cast.cells[lo:hi])
                dist = cast.distance_sigmas[lo:hi]
                self._grid.mark_observed(cells)
                updated += self._update_scan(cells, dist)
                if self._forget_beyond is not None:
                    self._forget(scans[first + s])
            give_back(cast)  # the next chunk's cells take its arrays: memory does not grow with the batch
            del cast
        self._scans_fused += len(scans)
        return IntegrationStats(
            scans=len(scans),
            rays=int(n_rays),
            cells_updated=int(updated),
            cells_traversed=traversed,
            rays_skipped=int(skipped),
        )

    # -- a prior: cells as agreeing scans made them ----------------------------------------
    def integrate_prior(self, levels: np.ndarray) -> IntegrationStats:
        """Fuse a prior: each cell as if ``|level|`` scans had agreed on it, hits (``level > 0``) or pass-throughs.

        ``levels`` is int8 of ``spec.shape``: ``PRIOR_UNSEEN`` leaves a cell as it is, 0 marks it observed
        with no evidence, ``+k`` / ``-k`` (``k <= MAX_PRIOR_SCANS``) marks it observed and fuses
        ``PRIOR_HIT_SIGMAS`` / ``PRIOR_PASS_SIGMAS`` into it ``k`` times with the map's own fusion: the
        cell then reads, and later scans change it, exactly as after ``k`` such scans. It has no pose and
        counts no scan. ``ValueError`` naming ``levels`` (the map unchanged) for a wrong shape, dtype or level.
        """
        levels = np.asarray(levels)
        if not isinstance(self.spec, GridSpec):
            raise ValueError("a prior is a fixed map's: a growing map has no box for its levels")
        if levels.shape != self.spec.shape or levels.dtype != np.int8:
            raise ValueError(f"levels must be int8 of the map's shape {self.spec.shape}, got {levels.dtype.name} of "
                             f"shape {levels.shape}")
        flat = levels.reshape(-1)
        seen = np.flatnonzero(flat != PRIOR_UNSEEN)
        counts = flat[seen].astype(np.int16)
        if counts.size and int(np.abs(counts).max()) > MAX_PRIOR_SCANS:
            raise ValueError(f"levels must lie in -{MAX_PRIOR_SCANS}..{MAX_PRIOR_SCANS} (or be PRIOR_UNSEEN, "
                             f"{PRIOR_UNSEEN}), got {int(counts[np.abs(counts).argmax()])}")
        ids = self._grid.ids(seen)
        order = np.argsort(ids, kind="stable")  # fusion takes its cells in increasing id (a block grid's order)
        ids, counts = ids[order], counts[order]
        self._grid.mark_observed(ids)
        updated = 0
        strength = np.abs(counts)
        for k in range(1, int(strength.max(initial=0)) + 1):
            agree = strength >= k
            distance = np.where(counts[agree] > 0, np.float32(PRIOR_HIT_SIGMAS), np.float32(PRIOR_PASS_SIGMAS))
            updated += self._update(ids[agree], distance)
        return IntegrationStats(scans=0, rays=0, cells_updated=updated)

    def prior_risks(self, weight: int) -> np.ndarray:
        """The risk of each level ``-weight .. weight`` of a prior, as this map reads a cell ``integrate_prior`` set
        to it from never observed: float32 of ``2 * weight + 1`` values (pass-throughs first, level 0 in the middle)."""
        _check_weight(weight)
        n = 2 * weight + 1
        probe = self._like(GridSpec(origin=(0.0, 0.0), size=(float(n), 1.0), resolution=1.0))
        probe.integrate_prior(np.arange(-weight, weight + 1, dtype=np.int8).reshape(n, 1))
        return np.array(probe.risk().reshape(-1))

    def prior_levels(self, occupancy: np.ndarray, weight: int) -> np.ndarray:
        """The prior level (``integrate_prior``) of each occupancy probability, int8 of ``occupancy``'s shape.

        NaN (unknown) is ``PRIOR_UNSEEN``, 1 (occupied) ``weight`` hits, 0 (free) ``weight``
        pass-throughs; any other probability the level among ``-weight .. weight`` whose risk
        (``prior_risks``) is nearest it, the one of fewer scans on a tie. ``ValueError`` for a
        probability outside [0, 1].
        """
        p = np.asarray(occupancy, dtype=np.float64)
        known = ~np.isnan(p)
        if np.any((p[known] < 0.0) | (p[known] > 1.0)):
            raise ValueError("occupancy must be probabilities in [0, 1] (NaN: unknown)")
        levels = np.arange(-weight, weight + 1)
        risks = self.prior_risks(weight).astype(np.float64)
        by_strength = np.argsort(np.abs(levels), kind="stable")  # argmin keeps the first of equals: fewer scans
        values, inverse = np.unique(p[known], return_inverse=True)
        nearest = levels[by_strength][np.argmin(np.abs(values[:, None] - risks[by_strength][None, :]), axis=1)]
        nearest[values == 1.0] = weight
        nearest[values == 0.0] = -weight
        out = np.full(p.shape, PRIOR_UNSEEN, dtype=np.int8)
        out[known] = nearest[inverse].astype(np.int8)
        return out

    def _like(self, spec: GridSpec) -> OccupancyMap:
        """A new map of this model, sensor (and engine) over ``spec``."""
        return type(self)(spec, self.sensor)

    def _cast_chunks(self, scans: list[Scan]) -> list[tuple[int, int]]:
        """Consecutive runs of scans ``[first, last)`` whose cast holds at most ``CAST_CHUNK_ENTRIES`` entries and
        ``CAST_CHUNK_BEAMS`` beams; a scan with more beams is a run of its own, cast in parts.

        A cast keeps an entry (12 bytes) per scan and cell reached; a scan reaches at most its
        rays times the cells along the map's diagonal, and at most every cell. Casting a whole
        batch at once made memory grow with the batch (12 scans of 16,384 beams on a 16 M-cell
        map: 3 GB); so did making the rays of every beam of a batch first (about 300
        bytes a beam: two scans of 2 M beams fused side by side took 1 GB). Chunks keep both
        bounded whatever the batch, with the same cells and evidence (each scan is cast on its
        own anyway).
        """
        spec = self.spec
        if isinstance(spec, GridSpec):
            reach, cells = math.ceil(math.hypot(*spec.shape)) + 1, spec.num_cells
        chunks: list[tuple[int, int]] = []
        first, held, held_beams = 0, 0, 0
        for s, scan in enumerate(scans):
            beams = scan.beam_count
            if not isinstance(spec, GridSpec):
                reach = math.ceil(math.sqrt(spec.ndim) * scan.range_max / spec.resolution) + 4
                cells = beams * reach
            entries = min(cells, beams * reach)
            # Forgetting frees blocks after each scan, and a cast's keys name blocks: one scan a cast then.
            if s > first and (held + entries > CAST_CHUNK_ENTRIES or held_beams + beams > CAST_CHUNK_BEAMS
                              or beams > CAST_CHUNK_BEAMS or self._forget_beyond is not None):
                chunks.append((first, s))
                first, held, held_beams = s, 0, 0
            held, held_beams = held + entries, held_beams + beams
        chunks.append((first, len(scans)))
        return chunks

    def _cast_in_parts(self, scan: Scan) -> tuple[CastResult, int, int]:
        """One scan's cast, ``CAST_CHUNK_BEAMS`` beams at a time; with its rays and the beams it dropped.

        Equal to the whole scan's cast: a cell's evidence is the largest of its beams', so the
        largest of the parts' (``np.fmax`` over the parts' entries of a cell). Memory: the
        parts' cells and one part's rays, whatever the scan's size and the map's.
        """
        traversed = n_rays = skipped = 0
        keys, dists = [], []
        for part in scan_parts(scan):
            rays = self._rays_of(scan, part)
            n_rays, skipped = n_rays + rays.ranges.size, skipped + rays.skipped
            cast = self._cast([scan], [rays], reuse=False)  # the parts' cells are all held until merged
            del rays
            traversed += int(cast.cells_traversed.sum())
            keys.append(cast.cells)
            dists.append(cast.distance_sigmas)
            del cast
        every = np.concatenate(keys)
        order = np.argsort(every, kind="stable")  # by key: a block's cells together, as a cast hands them out
        every, evidence = every[order], np.concatenate(dists)[order]
        first = np.flatnonzero(np.concatenate([[True], every[1:] != every[:-1]]))
        cells = every[first]
        best = np.fmax.reduceat(evidence, first) if every.size else evidence
        result = CastResult(cells=cells, distance_sigmas=best.astype(np.float32), scan_offsets=np.array([0, cells.size]),
                            cells_traversed=np.array([traversed]))
        return result, n_rays, skipped

    def _forget(self, scan: Scan) -> None:
        grid = cast(BlockGrid, self._grid)
        sensor = np.asarray(scan.pose[:2] if isinstance(scan, LaserScan) else scan.origin, dtype=np.float64)
        centre = (sensor - np.asarray(self.lattice.lower)) / self.lattice.resolution
        grid.forget_beyond(centre, cast(float, self._forget_beyond) / self.lattice.resolution)

    def _check_scan(self, scan: object, name: str) -> None:
        if self.growing:
            sensor = scan.pose[:2] if isinstance(scan, LaserScan) else getattr(scan, "origin", ())
            if any(abs(v) > MAX_COORDINATE_M for v in sensor):
                raise ValueError(f"{name}'s sensor is farther than {MAX_COORDINATE_M:.0e} m from the map frame's "
                                 "origin: use a local map frame")
        if isinstance(scan, LaserScan):
            if self.spec.ndim != 2:
                raise ValueError(f"{name} is a LaserScan, which is planar, and this map is 3-D; "
                                 "send its beams as a 3-D PointCloud (PointCloud.from_sensor_frame)")
        elif isinstance(scan, PointCloud):
            if scan.ndim != self.spec.ndim:
                raise ValueError(f"{name}.points must have shape (N, {self.spec.ndim}) for this "
                                 f"{self.spec.ndim}-D map, got {scan.points.shape}")
        else:
            raise ValueError(f"{name} must be a LaserScan or a PointCloud, got {type(scan).__name__}")

    def _checked(self, scans: Sequence[Scan]) -> list[Scan]:
        """``scans`` as a list, each checked against the map (``ValueError`` naming ``scans[i]``)."""
        scans = list(scans)
        for i, scan in enumerate(scans):
            self._check_scan(scan, f"scans[{i}]")
        return scans

    def _cast_chunk(self, scans: list[Scan], enter: bool = True) -> tuple[CastResult, int, int]:
        """The cast of a chunk of scans (``enter`` as :meth:`_cast`'s), with its beams and the readings skipped; their
        rays are gone before the chunk is fused."""
        rays = [self._rays_of(scan) for scan in scans]
        return self._cast(scans, rays, enter=enter), sum(r.ranges.size for r in rays), sum(r.skipped for r in rays)

    def _cast(self, scans: list[Scan], rays: list[Rays], reuse: bool = True, enter: bool = True) -> CastResult:
        """The cast of ``scans`` (their ``rays``); ``reuse``: into arrays a cast gave back (``raycast.give_back``),
        for a caller that gives this one back before its next cast; ``enter`` as :func:`~fuzzyocc.raycast.cast_into`'s
        (False: the map is left as it is)."""
        half_cell = 0.5 * self.spec.resolution
        counts = [r.ranges.size for r in rays]
        origins = np.repeat(np.stack([r.origin for r in rays]), counts, axis=0)
        directions = np.concatenate([r.directions for r in rays])
        ranges = np.concatenate([r.ranges for r in rays])
        hit = np.concatenate([r.hit for r in rays])
        sigma = np.concatenate([self.sensor.sigma(r.ranges, s.registration_sigma) * self._grazing(r)
                                for s, r in zip(scans, rays)])
        sigma = np.maximum(sigma, half_cell)
        index, shift = self._cast_blocks()
        cast = cast_into(
            self.lattice,
            index,
            shift,
            origins,
            directions,
            t_end=np.where(hit, ranges + self.occupied_extent * sigma, ranges),
            measured=np.where(hit, ranges, np.nan),
            sigma=sigma,
            ray_offsets=np.concatenate([[0], np.cumsum(counts)]),
            unknown_from=self.occupied_extent,
            reuse=reuse,
            enter=enter,
        )
        if enter:
            self._cast_done()
        return cast

    def _cast_blocks(self) -> tuple[BlockIndex, tuple[int, int, int]]:
        """The block index a cast numbers cells by, and its block size."""
        raise NotImplementedError

    def _cast_done(self) -> None:
        """After a cast: storage takes the blocks it added to the index."""

    def _stored_cells(self, keys: np.ndarray) -> np.ndarray:
        """The ids storage addresses the cells of a cast by (``keys`` as :func:`fuzzyocc.raycast.cast_into` gives them)."""
        return keys

    @property
    def incidence_floor(self) -> float:
        """Sigma along a beam is divided by ``max(sin(incidence), incidence_floor)``; 1 = incidence ignored."""
        return 1.0

    def _rays_of(self, scan: Scan, beams: slice | None = None) -> Rays:
        """The beams of ``scan`` (of its readings ``beams``, if given) as this model fuses them."""
        return scan.to_rays(beams=beams)

    def _grazing(self, rays: Rays) -> np.ndarray | float:
        """Factor on each beam's sigma for its incidence (1 where unknown or ignored)."""
        floor = self.incidence_floor
        if floor >= 1.0 or rays.incidence is None:
            return 1.0
        sine = rays.incidence
        return np.where(np.isfinite(sine), 1.0 / np.maximum(np.nan_to_num(sine, nan=1.0), floor), 1.0)

    # -- reading -------------------------------------------------------------------------
    def bounds(self) -> Window | None:
        """The smallest box of cells holding every observed cell; None while none is."""
        grid = self._grid
        if isinstance(grid, BlockGrid):
            found = grid.bounds()
            if found is None:
                return None
            lo, hi = (tuple(int(v) for v in a[: self.lattice.ndim]) for a in found)
        else:
            observed = grid.observed().reshape(cast(GridSpec, self.spec).shape)
            if not observed.any():
                return None
            where = np.nonzero(observed)
            lo = tuple(int(w.min()) for w in where)
            hi = tuple(int(w.max()) + 1 for w in where)
        return Window(lo, hi, self.lattice.resolution, self.lattice.lower)

    def window(self, low: Sequence[float] | None = None, high: Sequence[float] | None = None) -> Window | None:
        """The cells a read covers: a fixed map's box, a growing map's :meth:`bounds`, cut to the cells that meet
        ``[low, high]`` (metres; either may be omitted). None when nothing is left."""
        d = self.lattice.ndim
        spec = self.spec
        if isinstance(spec, GridSpec):
            whole: Window | None = Window((0,) * d, tuple(spec.shape), spec.resolution, self.lattice.lower)
        else:
            whole = self.bounds()
        if whole is None:
            return None
        lo, hi = list(whole.lo), list(whole.hi)
        res, lower = self.lattice.resolution, self.lattice.lower
        for name, corner in (("low", low), ("high", high)):
            if corner is None:
                continue
            values = [float(v) for v in corner]
            if len(values) != d or not all(math.isfinite(v) for v in values):
                raise ValueError(f"{name} must be {d} finite coordinates, got {list(corner)}")
            for a, v in enumerate(values):
                cell = math.floor((v - lower[a]) / res)
                if name == "low":
                    lo[a] = max(lo[a], cell)
                else:
                    hi[a] = min(hi[a], cell + 1)
        if any(h <= lo_ for lo_, h in zip(lo, hi)):
            return None
        return Window(tuple(lo), tuple(hi), res, lower)

    def window_around(self, points: object, margin: float, reach: float | None = None) -> Window:
        """A growing map's bounds and the cells of ``points`` ((M, D), metres), grown by ``margin`` metres on every
        side: what a plan between those points works on (beyond the bounds, never observed). ``reach``: only the
        part of that within ``reach`` metres of the points' box, on every axis."""
        if not self.growing:
            raise ValueError("window_around is for growing maps; a fixed map's plans work on its box")
        d, res = self.lattice.ndim, self.lattice.resolution
        pts = np.asarray(points, dtype=np.float64).reshape(-1, d)
        if not np.all(np.abs(pts) <= MAX_COORDINATE_M):
            raise ValueError(f"points must be finite and within {MAX_COORDINATE_M:.0e} m of the map frame's origin")
        pad = int(math.ceil(margin / res))
        cells = np.floor(pts / res).astype(np.int64)
        lo, hi = cells.min(axis=0) - pad, cells.max(axis=0) + 1 + pad
        bounds = self.bounds()
        if bounds is not None:
            lo = np.minimum(lo, np.asarray(bounds.lo) - pad)
            hi = np.maximum(hi, np.asarray(bounds.hi) + pad)
        if reach is not None:
            if not math.isfinite(reach) or reach < margin:
                raise ValueError(f"reach must be finite and at least the margin ({margin} m), got {reach}")
            out = int(math.ceil(reach / res))
            lo, hi = np.maximum(lo, cells.min(axis=0) - out), np.minimum(hi, cells.max(axis=0) + 1 + out)
        return Window(tuple(int(v) for v in lo), tuple(int(v) for v in hi), res, self.lattice.lower)

    def _box(self, window: Window) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = np.zeros(3, dtype=np.int64), np.ones(3, dtype=np.int64)
        lo[: len(window.lo)], hi[: len(window.hi)] = window.lo, window.hi
        return lo, hi

    def risk(self, window: Window | None = None) -> np.ndarray:
        """Risk of every cell of ``window`` (default: :meth:`window`, a fixed map's whole box), float32 of its
        shape in [0, 1], 0.5 = unknown.

        A new array each call (a snapshot: later integrations do not change it), marked
        read-only. The map caches risk as 16-bit fixed point, refreshed only where cells
        changed since the last read, so every value is a multiple of 2**-16
        (:data:`fuzzyocc.grid.RISK_STEP`): the model's risk to within 2**-17, 0.5
        exactly for unknown. It depends on the cell's state alone, so two maps with the
        same history, or a map and its :meth:`from_arrays` restoration, agree bit for bit.
        A growing map with nothing observed gives an empty array.
        """
        window = self.window() if window is None else window
        if window is None:
            out = np.zeros((0,) * self.lattice.ndim, dtype=np.float32)
        elif isinstance(self._grid, BlockGrid):
            out = self._grid.risk_in(*self._box(window)).reshape(window.shape)
        else:
            out = self._grid.risk().reshape(cast(GridSpec, self.spec).shape)[self._slices(window)].copy()
        out.flags.writeable = False
        return out

    def _slices(self, window: Window) -> tuple[slice, ...]:
        return tuple(slice(lo, hi) for lo, hi in zip(window.lo, window.hi))

    def plane_lookup(self, lut: np.ndarray, unobserved: int, window: Window | None = None) -> np.ndarray:
        """A 2-D map's cells of ``window`` (default :meth:`window`) through a table of its risk codes: (ny, nx)
        int8, rows along y.

        ``lut`` has an entry for each of the 65,536 risk codes (``lut[k]`` for risk
        ``k * RISK_STEP``, the values :meth:`risk` gives); cells no beam reached are
        ``unobserved``. One pass over the map, with no float copy: an OccupancyGrid or an
        image of a 16 M-cell map without its 64 MB of risk.
        """
        if self.lattice.ndim != 2:
            raise ValueError("plane_lookup is for 2-D maps; project a 3-D map's risk() instead")
        window = self.window() if window is None else window
        if window is None:
            return np.zeros((0, 0), dtype=np.int8)
        if isinstance(self._grid, BlockGrid):
            return self._grid.plane_lookup_in(*self._box(window), lut, unobserved)
        whole = self._grid.plane_lookup(lut, unobserved)
        return whole[window.lo[1]:window.hi[1], window.lo[0]:window.hi[0]].copy()

    def risk_at(self, points: object) -> np.ndarray:
        """Risk of the cells containing ``points`` ((M, D) map frame) -> (M,) float32 (a copy).

        Raises ``ValueError`` naming ``points`` if one is not finite or lies outside a fixed map's box (a
        growing map answers anywhere within ``MAX_COORDINATE_M``: 0.5 where never observed).
        """
        d = self.lattice.ndim
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != d:
            raise ValueError(f"points must have shape (M, {d}), got {pts.shape}")
        spec = self.spec
        if isinstance(spec, GridSpec):
            keys, valid = coords_to_keys(spec, pts)
            if not np.all(valid):
                bad = int(np.flatnonzero(~valid)[0])
                raise ValueError(f"points[{bad}] = {pts[bad].tolist()} is outside the map "
                                 f"[{list(spec.origin)}, {list(spec.upper)})")
            return self._grid.risk_of(keys_to_flat(spec, keys))
        far = ~np.all(np.abs(pts) <= MAX_COORDINATE_M, axis=1)  # NaN too
        if np.any(far):
            bad = int(np.flatnonzero(far)[0])
            raise ValueError(f"points[{bad}] = {pts[bad].tolist()} is not finite or farther than "
                             f"{MAX_COORDINATE_M:.0e} m from the map frame's origin")
        cells = np.zeros((pts.shape[0], 3), dtype=np.int64)
        cells[:, :d] = np.floor(pts / spec.resolution)
        return cast(BlockGrid, self._grid).risk_at(cells)

    def observed(self, window: Window | None = None) -> np.ndarray:
        """Cells some beam reached, bool of ``window``'s shape (default :meth:`window`; a new read-only array,
        like ``risk()``)."""
        window = self.window() if window is None else window
        if window is None:
            out = np.zeros((0,) * self.lattice.ndim, dtype=np.bool_)
        elif isinstance(self._grid, BlockGrid):
            out = self._grid.observed_in(*self._box(window)).reshape(window.shape)
        else:
            out = self._grid.observed().reshape(cast(GridSpec, self.spec).shape)[self._slices(window)].copy()
        out.flags.writeable = False
        return out

    # -- clearing ------------------------------------------------------------------------
    def clear(self, low: Sequence[float], high: Sequence[float]) -> int:
        """Set every cell from the one containing ``low`` to the one containing ``high`` (metres, inclusive, as
        octomap_server's ``clear_bbx``) back to never observed; returns how many cells were observed."""
        d = self.lattice.ndim
        lo_m, hi_m = (np.asarray(c, dtype=np.float64).reshape(-1) for c in (low, high))
        if lo_m.size != d or hi_m.size != d or not (np.all(np.isfinite(lo_m)) and np.all(np.isfinite(hi_m))):
            raise ValueError(f"low and high must be {d} finite coordinates each")
        if np.any(hi_m < lo_m):
            raise ValueError(f"high {hi_m.tolist()} must not be below low {lo_m.tolist()} along any axis")
        lower, res = np.asarray(self.lattice.lower), self.lattice.resolution
        bound = MAX_COORDINATE_M / res + 2
        lo = np.clip(np.floor((lo_m - lower) / res), -bound, bound).astype(np.int64)
        hi = np.clip(np.floor((hi_m - lower) / res) + 1, -bound, bound).astype(np.int64)
        grid = self._grid
        if isinstance(grid, BlockGrid):
            lo3, hi3 = np.zeros(3, dtype=np.int64), np.ones(3, dtype=np.int64)
            lo3[:d], hi3[:d] = lo, hi
            return grid.clear_box(lo3, hi3)
        spec = cast(GridSpec, self.spec)
        lo, hi = np.maximum(lo, 0), np.minimum(hi, spec.shape)
        if np.any(hi <= lo):
            return 0
        box = tuple(slice(a, b) for a, b in zip(lo, hi))
        flat = np.arange(spec.num_cells).reshape(spec.shape)[box].reshape(-1)
        was = int(np.count_nonzero(grid.observed()[flat]))
        grid.write(flat, np.zeros((flat.size, *grid.state.shape[1:]), dtype=grid.state.dtype))
        grid.clear_observed(flat)
        return was

    def state_nbytes(self) -> int:
        """Bytes of the map's persistent state: cell states and observed mask (1 bit a cell).

        What the map is, and what :meth:`to_arrays` must save (its observed array is
        unpacked to one byte a cell, its states to ``L`` bytes a cell). A :class:`FuzzyMap`
        keeps a block of cells in one state once (see :class:`fuzzyocc.grid.BlockGrid`):
        its figure is the block table, the blocks' shared states and the mixed blocks'
        cells. See :meth:`resident_nbytes` for the caches too.
        """
        return self._grid.persistent_nbytes()

    def held_cells(self) -> int:
        """Cells the map holds in memory: a :class:`FuzzyMap` one per cell of a mixed block and one per uniform
        block it holds (none for space no ray reached); a :class:`BayesMap` every cell of its box."""
        grid = self._grid
        return grid.held_cells() if isinstance(grid, BlockGrid) else self.spec.num_cells

    def resident_nbytes(self) -> int:
        """Bytes the map holds between calls: :meth:`state_nbytes` plus the risk cache.

        The risk cache is 2 bytes a cell (a :class:`FuzzyMap`: a cell of a mixed block, one
        code per uniform block), and a :class:`FuzzyMap` also counts its pool's spare slots.

        Not counted: arrays an integrate call allocates and frees (the ray caster's
        per-cell scratch, the batch's cells and evidence), and the engine's
        defuzzification tables, which are built once per engine and shared by every map
        using it.
        """
        return self._grid.resident_nbytes()

    # -- persistence ---------------------------------------------------------------------
    def _common_arrays(self) -> dict[str, np.ndarray]:
        return {
            "model": np.array(self.model),
            "observed": self._grid.observed().reshape(self.spec.shape),
            "scans_fused": np.array(self._scans_fused, dtype=np.int64),
        }

    @staticmethod
    def _take(arrays: dict[str, np.ndarray], key: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
        if key not in arrays:
            raise ValueError(f"arrays lacks {key!r}")
        arr = np.asarray(arrays[key])
        if arr.shape != shape or arr.dtype != dtype:
            raise ValueError(f"arrays[{key!r}] must be {np.dtype(dtype).name} of shape {shape}, "
                             f"got {arr.dtype.name} of shape {arr.shape}")
        return arr

    @classmethod
    def _common_from_arrays(cls, spec: GridSpec, arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, int]:
        _check_spec(spec)
        model = str(arrays.get("model", cls.model))
        if model != cls.model:
            raise ValueError(f"arrays hold a {model!r} map, not a {cls.model!r} one")
        observed = cls._take(arrays, "observed", spec.shape, np.bool_)
        scans = cls._take(arrays, "scans_fused", (), np.int64)
        if scans < 0:
            raise ValueError(f"arrays['scans_fused'] must be >= 0, got {int(scans)}")
        return observed.reshape(-1).copy(), int(scans)


class FuzzyMap(OccupancyMap):
    """Payeur's fuzzy occupancy map: L uint8 label activations per cell (11 for the default engine).

    Stored by uniform blocks (:class:`fuzzyocc.grid.BlockGrid`): a block of cells in one state
    (free space, unknown space, the inside of an obstacle) keeps that state once, so the map
    holds far less than ``L`` bytes a cell; states and risk are those of a dense grid bit for bit.

    Parameters
    ----------
    spec : GridSpec
        Region and resolution.
    sensor : SensorModel, optional
        Range and registration uncertainty (default ``SensorModel()``).
    engine : FuzzyEngine, optional
        Labels, membership functions, rule table, operators (default: the shipped default
        preset, :data:`fuzzyocc.presets.DEFAULT_PRESET`; ``FuzzyEngine.paper()`` for the paper's).
    """

    model = "fuzzy"

    def __init__(self, spec: GridSpec | LatticeSpec, sensor: SensorModel | None = None,
                 engine: FuzzyEngine | None = None) -> None:
        self.engine = presets.preset(presets.DEFAULT_PRESET) if engine is None else engine
        super().__init__(spec, sensor)

    @property
    def _blocks(self) -> BlockGrid:
        return cast(BlockGrid, self._grid)

    def _like(self, spec: GridSpec) -> FuzzyMap:
        return FuzzyMap(spec, self.sensor, self.engine)

    def _new_grid(self) -> BlockGrid:
        # Without the dense initial state: no block is held until a ray reaches it.
        box = self.spec.shape if isinstance(self.spec, GridSpec) else None
        return BlockGrid(self.spec.ndim, self._unknown_row(), self._risk_fn(), box)

    def _unknown_row(self) -> np.ndarray:
        return np.asarray(self.engine.unknown_state(), dtype=np.uint8)

    def _grid_from(self, state: np.ndarray, observed: np.ndarray) -> BlockGrid:
        return BlockGrid.from_dense(self.spec.shape, state, observed, self._unknown_row(), self._risk_fn())

    def _cast_blocks(self) -> tuple[BlockIndex, tuple[int, int, int]]:
        return self._blocks.index, self._blocks.block_shift

    def _cast_done(self) -> None:
        self._blocks.adopt()

    @property
    def occupied_extent(self) -> float:
        """The engine's: sigmas behind the surface past which its input is pure UNK."""
        return float(self.engine.occupied_extent)

    @property
    def incidence_floor(self) -> float:
        """The engine's (1 for the paper's: incidence ignored)."""
        return self.engine.incidence_floor

    def _rays_of(self, scan: Scan, beams: slice | None = None) -> Rays:
        if not isinstance(scan, LaserScan):
            return scan.to_rays(beams=beams)
        incidence, neighbours = self.engine.incidence_floor < 1.0, self.engine.no_return_neighbours
        if not neighbours:
            return scan.to_rays(incidence, beams)
        if beams is None:
            return scan.to_rays(incidence).cut_no_returns(neighbours)
        # a cut reads that many usable neighbours on each side: cut a wider part, keep this one's rays. The wide
        # part may span the whole scan (usable readings only at its ends): nothing but the cut is made of it
        wide = scan.widen(beams, neighbours)
        rays = scan.to_rays(False, wide).cut_no_returns(neighbours)
        before, own = scan.usable(slice(wide.start, beams.start)), scan.usable(beams)
        rays = rays.part(before, before + own, skipped=(beams.stop - beams.start) - own)
        if incidence:
            rays = dataclasses.replace(rays, incidence=scan.incidence_of(beams))
        return rays

    def _update(self, cells: np.ndarray, distance_sigmas: np.ndarray) -> int:
        if np.isnan(distance_sigmas).any():  # the cast never gives one: a NaN here is a bug upstream
            raise ValueError("distance_sigmas must not contain NaN")
        self._blocks.fuse(cells, distance_sigmas, self.engine.fuzzifier(), self.engine.row_fusion())
        return int(cells.size)

    def _update_scan(self, cells: np.ndarray, distance_sigmas: np.ndarray) -> int:
        # the fusion skips the -inf cells itself: filtering a lidar sweep's 7 M cells first copied 90 MB into fresh
        # memory a sweep
        self._update(cells, distance_sigmas)
        return int(cells.size - np.count_nonzero(distance_sigmas == -np.inf))

    def _risk_fn(self) -> Callable[[np.ndarray], np.ndarray]:
        return functools.partial(_defuzzified, self.engine)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Everything needed to restore the map bit for bit (copies): a fixed map's cells over its box, a growing
        map's blocks (:meth:`fuzzyocc.blockgrid.BlockGrid.to_blocks`)."""
        if self.growing:
            return self.snapshot_arrays()
        arrays = self._common_arrays()
        arrays["state"] = self._blocks.dense().reshape(*cast(GridSpec, self.spec).shape, -1)
        return self._engine_arrays(arrays)

    def snapshot_arrays(self, copy: bool = True) -> dict[str, np.ndarray]:
        """:meth:`to_arrays` as the blocks held, fixed maps too (copies; with ``copy=False`` views of the map's own
        arrays, valid while nothing changes the map): what a snapshot stores. Its cost follows what the map holds,
        not its box (a fixed map's cells over its box took 1.8 s for 6.9 M cells, mostly never observed);
        :meth:`from_arrays` restores either bit for bit."""
        arrays = {"model": np.array(self.model), "scans_fused": np.array(self._scans_fused, dtype=np.int64),
                  **self._blocks.to_blocks(copy)}
        return self._engine_arrays(arrays)

    def _engine_arrays(self, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        arrays["labels"] = np.array(self.engine.labels)
        if self._forget_beyond is not None:
            arrays["forget_beyond"] = np.array(self._forget_beyond, dtype=np.float64)
        return arrays

    @classmethod
    def from_arrays(cls, spec: GridSpec | LatticeSpec, sensor: SensorModel | None, arrays: dict[str, np.ndarray],
                    engine: FuzzyEngine | None = None) -> FuzzyMap:
        """A map restored from :meth:`to_arrays`; ``ValueError`` naming ``arrays`` if they do not fit."""
        engine = presets.preset(presets.DEFAULT_PRESET) if engine is None else engine
        labels = tuple(str(x) for x in np.asarray(arrays.get("labels", np.array(engine.labels))).ravel())
        if labels != tuple(engine.labels):
            raise ValueError(f"arrays hold labels {labels}, the engine has {tuple(engine.labels)}")
        if isinstance(spec, LatticeSpec) or "block_coords" in arrays:  # blocks: a growing map's, or a snapshot's
            if isinstance(spec, GridSpec):
                _check_spec(spec)
            model = str(arrays.get("model", cls.model))
            if model != cls.model:
                raise ValueError(f"arrays hold a {model!r} map, not a {cls.model!r} one")
            scans = int(cls._take(arrays, "scans_fused", (), np.int64))
            if scans < 0:
                raise ValueError(f"arrays['scans_fused'] must be >= 0, got {scans}")
            restored = cls(spec, sensor, engine)
            box = spec.shape if isinstance(spec, GridSpec) else None
            restored._grid = BlockGrid.from_blocks(spec.ndim, arrays, restored._unknown_row(), restored._risk_fn(),
                                                   box)
            restored._scans_fused = scans
        else:
            observed, scans = cls._common_from_arrays(spec, arrays)
            state = cls._take(arrays, "state", (*spec.shape, engine.num_labels), np.uint8)
            restored = cls(spec, sensor, engine)
            restored._restore(state.reshape(spec.num_cells, -1), observed, scans)  # compressed: a copy
        if "forget_beyond" in arrays:
            restored.forget_beyond = float(cls._take(arrays, "forget_beyond", (), np.float64))
        return restored


class BayesMap(OccupancyMap):
    """The paper's closed-form OPDF (eq. 4) merged by Bayes (eq. 3) as a sum of float32 log-odds.

    Log-odds 0 is unknown; each update is clamped to ``[bayes.CLAMP_MIN, bayes.CLAMP_MAX]``
    as OctoMap does, so a cell can change its mind. Risk is the probability.
    """

    model = "bayes"

    def __init__(self, spec: GridSpec, sensor: SensorModel | None = None) -> None:
        if isinstance(spec, LatticeSpec):
            raise ValueError("a BayesMap needs a fixed box (a GridSpec); growing maps are fuzzy maps")
        super().__init__(spec, sensor)
        # Only the cast numbers cells by block; the dense grid holds them by flat id.
        self._shift = block_shift_for(spec.ndim, spec.shape)
        self._index = BlockIndex()

    @property
    def _cells(self) -> CellGrid:
        return cast(CellGrid, self._grid)

    def _cast_blocks(self) -> tuple[BlockIndex, tuple[int, int, int]]:
        return self._index, self._shift

    def _stored_cells(self, keys: np.ndarray) -> np.ndarray:
        return flat_ids(keys, self._index, self._shift, self.spec.shape)

    def _initial_state(self) -> np.ndarray:
        return np.zeros(self.spec.num_cells, dtype=np.float32)

    @property
    def occupied_extent(self) -> float:
        """``bayes.BAYES_OCCUPIED_EXTENT``: past it the OPDF is 0.5 to within 1e-3."""
        return float(bayes.BAYES_OCCUPIED_EXTENT)

    def _update(self, cells: np.ndarray, distance_sigmas: np.ndarray) -> int:
        # In chunks: the OPDF's float64 temporaries would otherwise peak at ~100 MB for a 3-D sweep.
        for lo in range(0, cells.size, _BAYES_CHUNK):
            part = cells[lo : lo + _BAYES_CHUNK]
            evidence = bayes.logodds(bayes.opdf(distance_sigmas[lo : lo + _BAYES_CHUNK], 1.0))
            self._cells.write(part, bayes.update_logodds(self._cells.read(part), evidence))
        return int(cells.size)

    def _risk_fn(self) -> Callable[[np.ndarray], np.ndarray]:
        return _probability

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Everything needed to restore the map bit for bit (copies)."""
        return self.snapshot_arrays()

    def snapshot_arrays(self, copy: bool = True) -> dict[str, np.ndarray]:
        """What a snapshot stores: :meth:`to_arrays` (a Bayes map holds its whole box; ``copy`` as
        :meth:`FuzzyMap.snapshot_arrays`)."""
        arrays = self._common_arrays()
        logodds = self._cells.state.reshape(self.spec.shape)
        arrays["logodds"] = logodds.copy() if copy else logodds
        return arrays

    @classmethod
    def from_arrays(cls, spec: GridSpec, sensor: SensorModel | None, arrays: dict[str, np.ndarray]) -> BayesMap:
        """A map restored from :meth:`to_arrays`; ``ValueError`` naming ``arrays`` if they do not fit."""
        observed, scans = cls._common_from_arrays(spec, arrays)
        logodds = cls._take(arrays, "logodds", spec.shape, np.float32)
        if not np.all(np.isfinite(logodds)):
            raise ValueError("arrays['logodds'] must be finite")
        restored = cls(spec, sensor)
        restored._restore(logodds.reshape(-1).copy(), observed, scans)
        return restored
