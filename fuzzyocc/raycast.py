"""Exact grid traversal of range beams, with the per-scan "occupied before free" dedupe.

Pure geometry: rays in, cells and their crisp evidence (eq. 5 of the paper, in sigmas) out.
No map state is read or written here; the caller fuzzifies and fuses.

Traversal is Amanatides & Woo, "A fast voxel traversal algorithm for ray tracing" (1987):
every cell the segment passes through with a chord of positive length is visited exactly
once, none skipped; a segment through an exact corner may also visit one of the cells that
only touch it there (a zero-length chord). The segment of a ray is ``[0, t_end]`` along its
unit direction, clipped to the map box, so a sensor may sit outside the map. The end cell
(the one containing the point at ``t_end``) is included.

Position of a cell along a beam: the midpoint of the chord that the beam's *line* cuts
through the cell, ``0.5 * (t_enter + t_exit)``, unclipped by the segment's ends, so it
depends only on the cell and the line (not on where the traversal starts or stops). The
distance of eq. 5 is then ``(midpoint - measured_range) / sigma``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from fuzzyocc._block_ids import block_address, cell_id
from fuzzyocc.config import GridSpec

#: Distance (in sigmas) written for the cells of a no-return beam: free all the way, far to
#: the left of any membership function's support.
NO_RETURN_DISTANCE = -1.0e6

#: Distance written for a cell that the scan reached only past the occupied region of its
#: beams (pure UNK evidence): it counts as observed, and needs no update.
UNKNOWN_ONLY = -np.inf


@dataclass(frozen=True)
class CastResult:
    """Cells a batch of scans reaches, one entry per (scan, cell).

    Attributes
    ----------
    cells : (M,) ndarray of int64
        Cell ids: flat (C order over ``spec.shape``), or block by block with ``block_shift``
        (see :func:`cast_rays`); within a scan each cell appears once, in increasing order.
    distance_sigmas : (M,) ndarray of float32
        The evidence each cell takes from its scan: among the scan's beams through the cell,
        the largest ``(cell position - measured range) / sigma`` (the most occupied-ward) of
        those that bring evidence; ``NO_RETURN_DISTANCE`` for free space of a no-return
        beam; ``UNKNOWN_ONLY`` (-inf) where every beam reached the cell only at or past
        ``unknown_from`` sigmas behind its surface.
    scan_offsets : (S + 1,) ndarray of int64
        Scan ``s`` owns ``cells[scan_offsets[s]:scan_offsets[s + 1]]``.
    cells_traversed : (S,) ndarray of int64
        Cell visits of each scan before the dedupe (the ray-casting work).
    """

    cells: np.ndarray
    distance_sigmas: np.ndarray
    scan_offsets: np.ndarray
    cells_traversed: np.ndarray


@njit(cache=True, nogil=True, inline="always")
def _axis_setup(o, d, t0, lower, n, res):  # pragma: no cover - compiled
    """Cell index, step, next-boundary parameter, parameter per cell and last boundary on one axis."""
    if d == 0.0:
        k = min(max(np.int64(np.floor((o - lower) / res)), 0), n - 1)
        return k, 0, np.inf, np.inf, -np.inf
    u = (o + t0 * d - lower) / res
    i = np.floor(u)
    if d < 0.0 and u == i:  # on a face, going down: the segment is in the lower cell
        i -= 1.0
    k = min(max(np.int64(i), 0), n - 1)
    if d > 0.0:
        return k, 1, (lower + (k + 1) * res - o) / d, res / d, (lower + k * res - o) / d
    return k, -1, (lower + k * res - o) / d, -res / d, (lower + (k + 1) * res - o) / d


@njit(cache=True, nogil=True)
def _cast_kernel(origins, dirs, t_end, slope, offset, ray_offsets, lower, shape, res,
                 unknown_from, best, shift, nblk, planar):  # pragma: no cover - compiled; tested through cast_rays
    # ``planar`` is True for a 2-D map (one layer, rays in its plane), None for a 3-D one: numba
    # prunes the ``planar is None`` branches at compile time, so the 2-D traversal is compiled
    # without the z axis (a sixth less time on the bench's 2-D scene).
    # Evidence of a cell is ``slope * midpoint + offset`` (eq. 5 in sigmas; slope 0 for a
    # no-return). ``best`` is a scratch array over all cells, NaN everywhere on entry and on
    # exit: NaN means "not reached by the current scan", so the whole grid is never cleared.
    n_scans = ray_offsets.shape[0] - 1
    nx, ny, nz = shape[0], shape[1], shape[2]
    # Cell id: block id << block bits | offset in the block (``_block_ids``); with shift 0
    # (blocks of one cell) that is the flat id (ix * ny + iy) * nz + iz.
    hx, hy, hz = shift[0], shift[1], shift[2]
    nby, nbz = nblk[1], nblk[2]
    # This scan's cells, kept only while they are few enough for a sort (below an eighth of the
    # grid, see the dense sweep further down): at most 1 byte a cell of the grid, not 8.
    keep = best.shape[0] // 8 + 1
    touched = np.empty(keep, np.int64)  # fixed size: growing it in the hot loop slows the traversal
    cells = np.empty(1024, np.int64)
    dist = np.empty(1024, np.float32)
    scan_offsets = np.zeros(n_scans + 1, np.int64)
    traversed = np.zeros(n_scans, np.int64)
    n_out = 0
    for s in range(n_scans):
        n = 0
        visits = 0
        for r in range(ray_offsets[s], ray_offsets[s + 1]):
            ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
            dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
            # Clip [0, t_end] to the box (slab method).
            t0 = 0.0
            t1 = t_end[r]
            inside = True
            for a in range(3):
                o = origins[r, a]
                d = dirs[r, a]
                hi = lower[a] + shape[a] * res
                if d == 0.0:
                    if o < lower[a] or o >= hi:
                        inside = False
                else:
                    ta = (lower[a] - o) / d
                    tb = (hi - o) / d
                    if ta > tb:
                        ta, tb = tb, ta
                    t0 = max(t0, ta)
                    t1 = min(t1, tb)
            if not inside or not t0 < t1:
                continue
            ix, sx, tmx, tdx, px = _axis_setup(ox, dx, t0, lower[0], nx, res)
            iy, sy, tmy, tdy, py = _axis_setup(oy, dy, t0, lower[1], ny, res)
            if planar is None:
                iz, sz, tmz, tdz, pz = _axis_setup(oz, dz, t0, lower[2], nz, res)
                t_in = max(px, max(py, pz))  # where the line enters the first cell
            else:
                iz, sz, tmz, tdz = 0, 0, np.inf, np.inf
                t_in = max(px, py)
            a_ = slope[r]
            b_ = offset[r]
            while True:
                # Leave through the nearest face; ties step x, then y, then z.
                if planar is None:
                    if tmx <= tmy and tmx <= tmz:
                        t_out = tmx
                        ax = 0
                    elif tmy <= tmz:
                        t_out = tmy
                        ax = 1
                    else:
                        t_out = tmz
                        ax = 2
                    blk, off = block_address(ix, iy, iz, hx, hy, hz, nby, nbz)
                else:
                    ax = 0 if tmx <= tmy else 1
                    t_out = tmx if ax == 0 else tmy
                    blk, off = block_address(ix, iy, 0, hx, hy, hz, nby, nbz)
                c = cell_id(blk, off, hx, hy, hz)
                visits += 1
                v = a_ * (0.5 * (t_in + t_out)) + b_
                if v >= unknown_from:
                    v = -np.inf
                b = best[c]
                if b != b:
                    if n < keep:
                        touched[n] = c
                    n += 1
                    best[c] = v
                elif v > b:
                    best[c] = v
                if t_out >= t1:
                    break
                t_in = t_out
                if ax == 0:
                    ix += sx
                    if ix < 0 or ix >= nx:
                        break
                    tmx += tdx
                elif ax == 1:
                    iy += sy
                    if iy < 0 or iy >= ny:
                        break
                    tmy += tdy
                else:
                    iz += sz
                    if iz < 0 or iz >= nz:
                        break
                    tmz += tdz
        if n_out + n > cells.shape[0]:
            cap = max(2 * cells.shape[0], n_out + n)
            grown = np.empty(cap, np.int64)
            grown_d = np.empty(cap, np.float32)
            # element by element: a slice assignment would compile numba's shape-mismatch error
            # message formatting into this kernel (seconds more at the first start, on a cold cache)
            for q in range(n_out):
                grown[q] = cells[q]
                grown_d[q] = dist[q]
            cells = grown
            dist = grown_d
        # Hand the cells out in increasing id order, so that the map's reads and writes of
        # their states sweep memory instead of jumping about.
        if 8 * n >= best.shape[0]:  # dense (past keep): a sweep of the scratch is cheaper than a sort
            q = n_out
            for c in range(best.shape[0]):
                b = best[c]
                if b == b:
                    cells[q] = c
                    dist[q] = b
                    best[c] = np.nan
                    q += 1
        else:
            order = np.sort(touched[:n])
            for q in range(n):
                c = order[q]
                cells[n_out + q] = c
                dist[n_out + q] = best[c]
                best[c] = np.nan
        n_out += n
        scan_offsets[s + 1] = n_out
        traversed[s] = visits
    return cells[:n_out], dist[:n_out], scan_offsets, traversed  # views: a copy would double the peak


def _layout(spec: GridSpec, block_shift: tuple[int, int, int] | None) -> tuple[np.ndarray, np.ndarray]:
    """``(shift, blocks along each axis)`` of the cell numbering (3 axes; a 2-D grid is one layer)."""
    shape = np.ones(3, dtype=np.int64)
    shape[: spec.ndim] = spec.shape
    shift = np.zeros(3, dtype=np.int64) if block_shift is None else np.asarray(block_shift, dtype=np.int64)
    if shift.shape != (3,) or np.any(shift < 0) or np.any(shift > 8):
        raise ValueError(f"block_shift must be 3 integers in [0, 8], got {block_shift}")
    return shift, (shape + (1 << shift) - 1) >> shift


def new_scratch(spec: GridSpec, block_shift: tuple[int, int, int] | None = None) -> np.ndarray:
    """The scratch array :func:`cast_rays` needs (NaN over every cell id); reusable across calls."""
    shift, nblk = _layout(spec, block_shift)
    return np.full(int(np.prod(nblk)) << int(shift.sum()), np.nan, dtype=np.float32)


def cast_rays(
    spec: GridSpec,
    origins: np.ndarray,
    directions: np.ndarray,
    t_end: np.ndarray,
    measured: np.ndarray,
    sigma: np.ndarray,
    ray_offsets: np.ndarray,
    *,
    unknown_from: float,
    scratch: np.ndarray | None = None,
    block_shift: tuple[int, int, int] | None = None,
) -> CastResult:
    """Traverse the cells of every ray of a batch of scans and keep one evidence per (scan, cell).

    Parameters
    ----------
    spec : GridSpec
        The grid (2-D or 3-D).
    origins : (R, D) ndarray of float
        Start of each ray (the sensor), world frame, metres; may lie outside the map.
    directions : (R, D) ndarray of float
        Unit direction of each ray.
    t_end : (R,) ndarray of float
        Length of each ray's segment, metres (hit range plus the occupied region behind it,
        or ``range_max`` for a no-return).
    measured : (R,) ndarray of float
        Measured range of each ray, metres; NaN for a no-return (all its cells are free).
    sigma : (R,) ndarray of float
        Effective range sigma of each ray, metres, > 0.
    ray_offsets : (S + 1,) ndarray of int
        Scan ``s`` owns rays ``ray_offsets[s]:ray_offsets[s + 1]``; scans are deduped apart.
    unknown_from : float
        Distance (sigmas) at and past which the evidence is pure UNK.
    scratch : (num_cells,) float32 ndarray, optional
        From :func:`new_scratch` (with the same ``block_shift``); pass one to avoid allocating
        it per call. NaN on return.
    block_shift : (3,) ints, optional
        Number cells block by block, for a map stored in blocks of ``2**block_shift[a]`` cells
        along axis ``a`` (x, y, z; a 2-D grid has one z layer): the id of cell ``(i, j, k)`` is
        ``block << sum(block_shift) | offset``, ``block`` the C-order index of
        ``(i >> sx, j >> sy, k >> sz)`` among the blocks covering the grid and ``offset`` the
        C-order index of ``(i & mx, j & my, k & mz)`` in its block. Default: flat ids.

    Returns
    -------
    CastResult
    """
    d = spec.ndim
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    n_rays = origins.shape[0]
    if origins.shape != (n_rays, d) or directions.shape != (n_rays, d):
        raise ValueError(f"origins and directions must both have shape (R, {d}), got {origins.shape}, {directions.shape}")
    if not (np.isfinite(origins).all() and np.isfinite(directions).all()
            and np.isfinite(np.asarray(t_end, dtype=np.float64)).all()):
        # the kernel trusts them: a NaN direction made it hand out cell ids it never wrote (out of bounds)
        raise ValueError("origins, directions and t_end must be finite")
    offsets = np.asarray(ray_offsets, dtype=np.int64)
    if offsets.ndim != 1 or offsets.size < 1 or offsets[0] != 0 or offsets[-1] != n_rays or np.any(np.diff(offsets) < 0):
        raise ValueError("ray_offsets must rise from 0 to the number of rays")
    lower = np.zeros(3)
    lower[:d] = spec.origin
    shape = np.ones(3, dtype=np.int64)
    shape[:d] = spec.shape
    if d == 2:
        # A 2-D map is a 3-D one of a single layer; rays lie in its mid-plane.
        origins = np.concatenate([origins, np.full((n_rays, 1), 0.5 * spec.resolution)], axis=1)
        directions = np.concatenate([directions, np.zeros((n_rays, 1))], axis=1)
    measured = np.asarray(measured, dtype=np.float64)
    no_return = np.isnan(measured)
    slope = np.where(no_return, 0.0, 1.0 / np.asarray(sigma, dtype=np.float64))
    shift, nblk = _layout(spec, block_shift)
    n_ids = int(np.prod(nblk)) << int(shift.sum())
    if scratch is None:
        scratch = np.full(n_ids, np.nan, dtype=np.float32)
    elif scratch.shape != (n_ids,) or scratch.dtype != np.float32:
        raise ValueError("scratch must come from new_scratch(spec, block_shift)")
    cells, dist, scan_offsets, traversed = _cast_kernel(
        np.ascontiguousarray(origins),
        np.ascontiguousarray(directions),
        np.ascontiguousarray(t_end, dtype=np.float64),
        slope,
        np.where(no_return, NO_RETURN_DISTANCE, -measured * slope),
        offsets,
        lower,
        shape,
        float(spec.resolution),
        float(unknown_from),
        scratch,
        shift,
        nblk,
        True if d == 2 else None,
    )
    return CastResult(cells=cells, distance_sigmas=dist, scan_offsets=scan_offsets, cells_traversed=traversed)


#: What ``traversal_cells`` answers for a segment with a NaN or infinite end: more than any budget
UNBOUNDED_CELLS = 2**62


@njit(cache=True, nogil=True)
def _traversal_kernel(origin, ends, lower, upper, res):  # pragma: no cover - compiled
    total = 0
    for i in range(ends.shape[0]):
        enter, leave = 0.0, 1.0
        for k in range(ends.shape[1]):
            o = origin[k]
            d = ends[i, k] - o
            if not np.isfinite(d):  # an end point beyond what floats hold, or NaN
                return UNBOUNDED_CELLS
            if d == 0.0:  # never crosses this axis's slab: all of the segment, or none of it
                if o < lower[k] or o > upper[k]:
                    enter, leave = 1.0, 0.0
                continue
            t_a, t_b = (lower[k] - o) / d, (upper[k] - o) / d
            enter = max(enter, min(t_a, t_b))
            leave = min(leave, max(t_a, t_b))
        if not (leave > enter):  # outside the box
            continue
        # the L1 length of the part inside the box, axis by axis: each term is at most the box's side, so a
        # segment of 1e308 m (a finite range_max) cannot overflow it
        inside = 0.0
        for k in range(ends.shape[1]):
            inside += abs(ends[i, k] - origin[k]) * (leave - enter)
        cells = np.ceil(inside / res)
        if not (cells < UNBOUNDED_CELLS):  # inf or NaN: an end point beyond what floats hold
            return UNBOUNDED_CELLS
        total += int(cells) + 1
        if total >= UNBOUNDED_CELLS:
            return UNBOUNDED_CELLS
    return total


def traversal_cells(spec: GridSpec, origin: np.ndarray, ends: np.ndarray) -> int:
    """About how many cells a cast walks for the segments ``origin`` -> each of ``ends`` ((N, D), metres).

    Each segment is clipped to the map's box (the cast never walks outside it), and walks one
    cell per cell boundary it crosses: its L1 length in cells, plus its first cell. A bound
    known before any cell is touched, for refusing work that is too large (the band a cast
    walks past a hit adds a few cells a ray, not counted). Compiled and without the GIL: the
    service estimates every batch before it is stored, refused ones too.
    """
    origin = np.ascontiguousarray(origin, dtype=np.float64).reshape(-1)
    ends = np.ascontiguousarray(ends, dtype=np.float64).reshape(-1, origin.size)
    lower = np.asarray(spec.origin, dtype=np.float64)
    upper = lower + np.asarray(spec.shape, dtype=np.float64) * spec.resolution
    return int(_traversal_kernel(origin, ends, lower, upper, float(spec.resolution)))
