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

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit

from fuzzyocc import parallel
from fuzzyocc._block_table import BlockIndex, _home, find, insert
from fuzzyocc.config import MAX_COORDINATE_M, GridSpec, LatticeSpec

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
    new_blocks : (K, 3) ndarray of int32, or None
        For a cast made with ``enter=False``: the blocks it reached that its index lacked, whose slots its cells
        already name (from the index's count on, in this order); :func:`enter_new_blocks` enters them. None when
        the cast entered them itself.
    index_at : (int, int)
        The index's count of blocks and of blocks dropped when the cast was made: it still fits the index while
        both are unchanged (blocks are only ever appended or dropped).
    """

    cells: np.ndarray
    distance_sigmas: np.ndarray
    scan_offsets: np.ndarray
    cells_traversed: np.ndarray
    new_blocks: np.ndarray | None = None
    index_at: tuple[int, int] = (0, 0)


@njit(cache=True, nogil=True, inline="always")
def _axis_setup(o, d, t0, lower, n, res):  # pragma: no cover - compiled
    """Cell index, step, next-boundary parameter, parameter per cell and last boundary on one axis.

    The index is clamped to ``[0, n)`` on a bounded grid; ``n`` 0 stands for an unbounded lattice."""
    if d == 0.0:
        k = np.int64(np.floor((o - lower) / res))
        if n > 0:
            k = min(max(k, 0), n - 1)
        return k, 0, np.inf, np.inf, -np.inf
    u = (o + t0 * d - lower) / res
    i = np.floor(u)
    if d < 0.0 and u == i:  # on a face, going down: the segment is in the lower cell
        i -= 1.0
    k = np.int64(i)
    if n > 0:
        k = min(max(k, 0), n - 1)
    if d > 0.0:
        return k, 1, (lower + (k + 1) * res - o) / d, res / d, (lower + k * res - o) / d
    return k, -1, (lower + k * res - o) / d, -res / d, (lower + (k + 1) * res - o) / d


@njit(cache=True, nogil=True, inline="always")
def _clipped(origins, dirs, t_end, r, lower, shape, res, bounded):  # pragma: no cover - compiled
    """``[t0, t1]`` of ray ``r`` within the box (``bounded`` True) or as it is; empty when ``t1 <= t0``."""
    t0 = 0.0
    t1 = t_end[r]
    if bounded is not None:
        # slab method
        for a in range(3):
            o = origins[r, a]
            d = dirs[r, a]
            hi = lower[a] + shape[a] * res
            if d == 0.0:
                if o < lower[a] or o >= hi:
                    return 0.0, -1.0
            else:
                ta = (lower[a] - o) / d
                tb = (hi - o) / d
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
    return t0, t1


@njit(cache=True, nogil=True, inline="always")
def _block_at(o, d, t, lower, n, res, h):  # pragma: no cover - compiled
    """Block coordinate, along one axis, of the cell holding the point at ``t`` (clamped to ``[0, n)`` if ``n``)."""
    k = np.int64(np.floor((o + t * d - lower) / res))
    if n > 0:
        k = min(max(k, 0), n - 1)
    return k >> h


_u = np.uint64

#: The largest set of a walk's rows kept for the next cast (``_WALK_ROWS``): an Ouster frame's in one walk, 262,144
#: rows of a 3-D block's 64 cells (64 MiB of scratch, 7 MiB of their blocks' coordinates, slots and window entries).
SPARE_ROWS_BYTES = 71 << 20
#: The largest arrays of a cast's cells kept for the next (``give_back``): a lidar sweep's at 0.1 m.
SPARE_CELLS_BYTES = 128 << 20
#: Most entries of a scan's window of blocks (int32 each, 8 MiB): a scan whose rays span more blocks finds each block
#: in the hash alone.
WINDOW_LIMIT = 1 << 21


@njit(cache=True, nogil=True)
def _walk(origins, dirs, t_end, slope, offset, ray_lo, ray_hi, lower, shape, res, unknown_from, shift, tkeys, tslots,
          window_limit, planar, bounded, scratch, rcoords, rslot, went):  # pragma: no cover - compiled
    # One thread's share of a cast: rays ``ray_lo[s]:ray_hi[s]`` of each scan ``s``, each cell's evidence kept in a
    # scratch row of its block (one row per block a scan reached), the largest of the scan's beams through it. The
    # map's index is only read here (several walks run at once): a row carries its block's coordinates and slot,
    # -1 for a block not in the index yet, which ``_combine`` enters.
    # ``planar`` is True for a 2-D map (one layer, rays in its plane), None for a 3-D one: numba prunes the
    # ``planar is None`` branches at compile time, so the 2-D traversal is compiled without the z axis (a sixth
    # less time on the bench's 2-D scene). ``bounded`` True clips rays to the box of ``shape`` cells from
    # ``lower``; None walks the unbounded lattice whose cell 0 starts at ``lower``.
    # Evidence of a cell is ``slope * midpoint + offset`` (eq. 5 in sigmas; slope 0 for a no-return).
    # A ray enters a new block every two cells or so: a dense window over the blocks the scan's rays span
    # (``window``, -1 between scans) gives a block's row in one read; a block outside it is found in a small
    # table of the scan's own (``pkeys``), so that the cost follows the cells the rays cross, never the map's extent.
    # ``scratch`` (all NaN), ``rcoords``, ``rslot`` and ``went`` are the rows to start with (``_WALK_ROWS``); they grow
    # here and come back with the walk.
    n_scans = ray_lo.shape[0]
    nx, ny, nz = shape[0], shape[1], shape[2]
    hx, hy, hz = shift[0], shift[1], shift[2]
    mx, my, mz = (1 << hx) - 1, (1 << hy) - 1, (1 << hz) - 1
    window = np.full(0, -1, np.int32)
    pkeys = np.empty((256, 3), np.int64)
    pvals = np.full(256, -1, np.int64)
    pused = np.empty(128, np.int64)
    n_pused = 0
    row_offsets = np.zeros(n_scans + 1, np.int64)
    traversed = np.zeros(n_scans, np.int64)
    nt = 0
    written = 0  # cells of the rows that hold evidence
    none = np.int64(-1) << 62
    for s in range(n_scans):
        row_offsets[s] = nt
        first_row = nt
        # The scan's window: the blocks of its segments' ends, one block more on each side (rounding).
        lo_x, lo_y, lo_z = np.int64(1) << 62, np.int64(1) << 62, np.int64(1) << 62
        hi_x, hi_y, hi_z = -lo_x, -lo_y, -lo_z
        for r in range(ray_lo[s], ray_hi[s]):
            t0, t1 = _clipped(origins, dirs, t_end, r, lower, shape, res, bounded)
            if not t0 < t1:
                continue
            for t in (t0, t1):
                bx = _block_at(origins[r, 0], dirs[r, 0], t, lower[0], nx, res, hx)
                by = _block_at(origins[r, 1], dirs[r, 1], t, lower[1], ny, res, hy)
                bz = _block_at(origins[r, 2], dirs[r, 2], t, lower[2], nz, res, hz)
                lo_x, lo_y, lo_z = min(lo_x, bx), min(lo_y, by), min(lo_z, bz)
                hi_x, hi_y, hi_z = max(hi_x, bx), max(hi_y, by), max(hi_z, bz)
        wx0, wy0, wz0 = lo_x - 1, lo_y - 1, lo_z - 1
        wnx, wny, wnz = hi_x - lo_x + 3, hi_y - lo_y + 3, hi_z - lo_z + 3
        if planar is not None:
            wz0, wnz = 0, 1
        if wnx < 3 or wnx > window_limit or wny > window_limit or wnz > window_limit \
                or wnx * wny > window_limit or wnx * wny * wnz > window_limit:
            wnx = wny = wnz = 0  # no ray, or too wide: the scan's table alone
        elif wnx * wny * wnz > window.shape[0]:
            window = np.full(wnx * wny * wnz, -1, np.int32)
        visits = 0
        last_x, last_y, last_z = none, np.int64(0), np.int64(0)
        row = 0
        for r in range(ray_lo[s], ray_hi[s]):
            t0, t1 = _clipped(origins, dirs, t_end, r, lower, shape, res, bounded)
            if not t0 < t1:
                continue
            # Growing an array inside the walk below would make numba count references at every cell: when
            # the rows or the table are full, the walk stops, they grow here, and the ray is walked again
            # (a cell's evidence is a maximum: walking a ray twice writes what once does).
            while True:
                full = 0
                last_x = none
                ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
                dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
                ix, sx, tmx, tdx, px = _axis_setup(ox, dx, t0, lower[0], nx, res)
                iy, sy, tmy, tdy, py = _axis_setup(oy, dy, t0, lower[1], ny, res)
                if planar is None:
                    iz, sz, tmz, tdz, pz = _axis_setup(oz, dz, t0, lower[2], nz, res)
                    t_in = max(px, max(py, pz))  # where the line enters the first cell
                else:
                    iz, sz, tmz, tdz = 0, 0, np.inf, np.inf
                    t_in = max(px, py)
                ix0, iy0, iz0 = ix, iy, iz
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
                    else:
                        ax = 0 if tmx <= tmy else 1
                        t_out = tmx if ax == 0 else tmy
                    bx, by, bz = ix >> hx, iy >> hy, iz >> hz
                    qx, qy, qz = bx - wx0, by - wy0, bz - wz0
                    # Unsigned: one compare per axis for the window's two bounds, and numba indexes by an unsigned
                    # integer without its negative-index wraparound (a sixth of the 2-D walk's time, with both).
                    if planar is None:
                        inside = _u(qx) < _u(wnx) and _u(qy) < _u(wny) and _u(qz) < _u(wnz)
                    else:
                        inside = _u(qx) < _u(wnx) and _u(qy) < _u(wny)
                    if inside:
                        # In the window: one read, and no branch on the block changing (it does every two cells).
                        w = (qx * wny + qy) * wnz + qz if planar is None else qx * wny + qy
                        row = window[_u(w)]
                        last_x = none
                        if row < 0:
                            if nt == rslot.shape[0]:
                                full = 1
                                break
                            row = nt
                            nt += 1
                            _open_row(row, bx, by, bz, w, rcoords, rslot, went, tkeys, tslots)
                            window[_u(w)] = row
                    elif bx != last_x or by != last_y or bz != last_z:
                        pmask = pvals.shape[0] - 1
                        h = _home(bx, by, bz, pmask)
                        row = -1
                        while pvals[h] >= 0:
                            if pkeys[h, 0] == bx and pkeys[h, 1] == by and pkeys[h, 2] == bz:
                                row = pvals[h]
                                break
                            h = (h + 1) & pmask
                        if row < 0:
                            if nt == rslot.shape[0]:
                                full = 1
                                break
                            if 2 * (n_pused + 1) > pvals.shape[0]:
                                full = 2
                                break
                            row = nt
                            nt += 1
                            _open_row(row, bx, by, bz, -1, rcoords, rslot, went, tkeys, tslots)
                            pkeys[h, 0], pkeys[h, 1], pkeys[h, 2] = bx, by, bz
                            pvals[h] = row
                            pused[n_pused] = h
                            n_pused += 1
                        last_x, last_y, last_z = bx, by, bz
                    off = ((ix & mx) << hy | (iy & my)) << hz | (iz & mz)
                    v = a_ * (0.5 * (t_in + t_out)) + b_
                    if v >= unknown_from:
                        v = -np.inf
                    ur, uo = _u(row), _u(off)
                    b = scratch[ur, uo]
                    if b != b:
                        written += 1
                        scratch[ur, uo] = v
                    elif v > b:
                        scratch[ur, uo] = v
                    if t_out >= t1:
                        break
                    t_in = t_out
                    if ax == 0:
                        ix += sx
                        if bounded is not None and (ix < 0 or ix >= nx):
                            ix -= sx
                            break
                        tmx += tdx
                    elif ax == 1:
                        iy += sy
                        if bounded is not None and (iy < 0 or iy >= ny):
                            iy -= sy
                            break
                        tmy += tdy
                    else:
                        iz += sz
                        if bounded is not None and (iz < 0 or iz >= nz):
                            iz -= sz
                            break
                        tmz += tdz
                if full == 0:
                    # every step moves one index by one: the cells visited, without a count in the walk
                    visits += 1 + abs(ix - ix0) + abs(iy - iy0) + abs(iz - iz0)
                    break
                if full == 1:
                    scratch, rcoords, rslot, went = _grown_rows(scratch, rcoords, rslot, went, nt)
                else:
                    pkeys, pvals, pused = _grown_table(pkeys, pvals, pused, n_pused, rcoords, went, first_row, nt)
        # Leave the window and the table empty for the next scan: the cost follows the rows, not their size.
        for q in range(first_row, nt):
            if went[q] >= 0:
                window[_u(went[q])] = -1
        for q in range(n_pused):
            pvals[pused[q]] = -1
        n_pused = 0
        traversed[s] = visits
    row_offsets[n_scans] = nt
    return scratch, rcoords, rslot, row_offsets, traversed, went, written


@njit(cache=True, nogil=True, inline="always")
def _open_row(row, bx, by, bz, w, rcoords, rslot, went, tkeys, tslots):  # pragma: no cover - compiled
    """Row ``row`` is block ``(bx, by, bz)``'s in this scan: its coordinates, its slot in the index (-1: not there
    yet) and its window entry ``w`` (-1: outside the window)."""
    rcoords[row, 0], rcoords[row, 1], rcoords[row, 2] = bx, by, bz
    rslot[row] = find(tkeys, tslots, bx, by, bz)
    went[row] = w


@njit(cache=True, nogil=True)
def _grown_rows(scratch, rcoords, rslot, went, n):  # pragma: no cover - compiled
    """The rows of a walk with room for twice as many (the first ``n`` kept)."""
    cap = 2 * rslot.shape[0]
    grown = np.full((cap, scratch.shape[1]), np.nan, np.float32)
    coords = np.empty((cap, 3), np.int32)
    slots = np.empty(cap, np.int64)
    entries = np.empty(cap, np.int64)
    # element by element: a slice assignment would compile numba's shape-mismatch error message formatting into
    # the kernel (seconds more at the first start, on a cold cache)
    for q in range(n):
        for o in range(scratch.shape[1]):
            grown[q, o] = scratch[q, o]
        coords[q, 0], coords[q, 1], coords[q, 2] = rcoords[q, 0], rcoords[q, 1], rcoords[q, 2]
        slots[q] = rslot[q]
        entries[q] = went[q]
    return grown, coords, slots, entries


@njit(cache=True, nogil=True)
def _grown_table(pkeys, pvals, pused, n_pused, rcoords, went, first, n):  # pragma: no cover - compiled
    """A scan's table of blocks outside its window, twice the size, holding its rows ``first:n`` outside it."""
    cap = 2 * pvals.shape[0]
    keys = np.empty((cap, 3), np.int64)
    vals = np.full(cap, -1, np.int64)
    used = np.empty(cap // 2, np.int64)
    mask = cap - 1
    k = 0
    for q in range(first, n):
        if went[q] >= 0:
            continue
        h = _home(rcoords[q, 0], rcoords[q, 1], rcoords[q, 2], mask)
        while vals[h] >= 0:
            h = (h + 1) & mask
        keys[h, 0], keys[h, 1], keys[h, 2] = rcoords[q, 0], rcoords[q, 1], rcoords[q, 2]
        vals[h] = q
        used[k] = h
        k += 1
    return keys, vals, used


@njit(cache=True, nogil=True)
def _new_blocks(rcoords, rslot, n):  # pragma: no cover - compiled
    """The coordinates of the blocks rows ``:n`` reached that the index lacks, each once, in lexicographic order:
    the order the index takes them in, whatever the split of the rays between walks."""
    fresh = np.flatnonzero(rslot[:n] < 0)
    order = fresh
    for a in (2, 1, 0):  # a stable sort per axis, last axis first: lexicographic
        order = order[np.argsort(rcoords[order, a], kind="mergesort")]
    out = np.empty((order.shape[0], 3), np.int32)
    k = 0
    for q in order:
        if k > 0 and rcoords[q, 0] == out[k - 1, 0] and rcoords[q, 1] == out[k - 1, 1] \
                and rcoords[q, 2] == out[k - 1, 2]:
            continue
        out[k, 0], out[k, 1], out[k, 2] = rcoords[q, 0], rcoords[q, 1], rcoords[q, 2]
        k += 1
    return out[:k]


@njit(cache=True, nogil=True)
def _slot_new(rcoords, rslot, new, first):  # pragma: no cover - compiled
    """The rows of blocks not in the index (``rslot`` -1) take the slots ``_enter`` gives ``new`` (their blocks,
    lexicographic, each once) from ``first`` on: found by bisection."""
    for q in range(rslot.shape[0]):
        if rslot[q] >= 0:
            continue
        lo, hi = 0, new.shape[0]
        while lo < hi:
            mid = (lo + hi) >> 1
            if (new[mid, 0], new[mid, 1], new[mid, 2]) < (rcoords[q, 0], rcoords[q, 1], rcoords[q, 2]):
                lo = mid + 1
            else:
                hi = mid
        rslot[q] = first + lo


@njit(cache=True, nogil=True)
def _enter(blocks, tkeys, tslots, coords, n_slots):  # pragma: no cover - compiled
    """Enter ``blocks`` (absent) into the index at the next slots; the index must have room. Its new count."""
    for q in range(blocks.shape[0]):
        insert(tkeys, tslots, blocks[q, 0], blocks[q, 1], blocks[q, 2], n_slots)
        coords[n_slots, 0], coords[n_slots, 1], coords[n_slots, 2] = blocks[q, 0], blocks[q, 1], blocks[q, 2]
        n_slots += 1
    return n_slots


@njit(cache=True, nogil=True)
def _combine(scratches, rcoords, rslot, row_offsets, tkeys, tslots, bits, n_cells, cells, dist):  # pragma: no cover
    """The walks' rows as one cast: per scan, its cells by increasing key, a cell reached by several walks with the
    largest of their evidence. ``scratches`` are the walks' scratch rows, ``rcoords`` and ``rslot`` their rows'
    blocks one walk after the other, ``row_offsets`` (walks, scans + 1) the rows of walk ``p``, scan ``s`` in them;
    every block is in the index now. Each scratch row is NaN again after (the walks' rows are used again). ``cells``
    and ``dist`` are written if they have room for ``n_cells`` (the walks' cells with evidence, the most there can
    be), else new arrays; with the number of cells written."""
    n_parts, n_scans = row_offsets.shape[0], row_offsets.shape[1] - 1
    block_cells = scratches[0].shape[1]
    n_rows = rslot.shape[0]
    part = np.empty(n_rows, np.int64)  # each row's walk, and its row there
    local = np.empty(n_rows, np.int64)
    start = np.zeros(n_parts + 1, np.int64)  # the first row of each walk in ``rcoords`` and ``rslot``
    q = 0
    for p in range(n_parts):
        start[p + 1] = start[p] + row_offsets[p, n_scans]
        for k in range(row_offsets[p, n_scans]):
            part[q] = p
            local[q] = k
            q += 1
    for q in range(n_rows):
        if rslot[q] < 0:
            rslot[q] = find(tkeys, tslots, rcoords[q, 0], rcoords[q, 1], rcoords[q, 2])
    if cells.shape[0] < n_cells:
        cells = np.empty(n_cells, np.int64)
        dist = np.empty(n_cells, np.float32)
    scan_offsets = np.zeros(n_scans + 1, np.int64)
    n_out = 0
    for s in range(n_scans):
        scan_offsets[s] = n_out
        count = 0
        for p in range(n_parts):
            count += row_offsets[p, s + 1] - row_offsets[p, s]
        rows = np.empty(count, np.int64)
        k = 0
        for p in range(n_parts):
            for q in range(row_offsets[p, s], row_offsets[p, s + 1]):
                rows[k] = start[p] + q
                k += 1
        rows = rows[np.argsort(rslot[rows], kind="mergesort")]
        i = 0
        while i < count:
            j = i + 1
            while j < count and rslot[rows[j]] == rslot[rows[i]]:
                j += 1
            base = rslot[rows[i]] << bits
            if j == i + 1:  # a block one walk reached (most): its row read straight
                row = scratches[part[rows[i]]][local[rows[i]]]
                for o in range(block_cells):
                    v = row[o]
                    if v == v:
                        row[o] = np.nan
                        cells[n_out] = base | o
                        dist[n_out] = v
                        n_out += 1
                i = j
                continue
            for o in range(block_cells):
                b = np.float32(np.nan)
                for m in range(i, j):
                    scratch = scratches[part[rows[m]]]
                    v = scratch[local[rows[m]], o]
                    if v == v:
                        scratch[local[rows[m]], o] = np.nan
                        if b != b or v > b:
                            b = v
                if b == b:
                    cells[n_out] = base | o
                    dist[n_out] = b
                    n_out += 1
            i = j
    scan_offsets[n_scans] = n_out
    return cells, dist, scan_offsets, n_out


class _Spares:
    """Arrays kept between casts for the next to write into, at most ``count_per_thread`` sets a thread of up to
    ``max_bytes``: memory written for the first time costs far more than its use (in six Ouster frames, the walks'
    rows growing took 156 k page faults and the cells written into fresh arrays 114 k)."""

    def __init__(self, max_bytes: int, count_per_thread: int) -> None:
        self.max_bytes, self.count_per_thread = max_bytes, count_per_thread
        self._lock = threading.Lock()
        self._spare: list[tuple[np.ndarray, ...]] = []

    def take(self, fits: Callable[[tuple[np.ndarray, ...]], bool]) -> tuple[np.ndarray, ...] | None:
        """A kept set that ``fits``, taken out; None when none does."""
        with self._lock:
            for k, arrays in enumerate(self._spare):
                if fits(arrays):
                    return self._spare.pop(k)
        return None

    def give(self, arrays: tuple[np.ndarray, ...]) -> None:
        """Keep ``arrays`` for a later cast, unless they are too big or enough are kept."""
        with self._lock:
            if (sum(a.nbytes for a in arrays) <= self.max_bytes
                    and len(self._spare) < self.count_per_thread * parallel.threads()):
                self._spare.append(arrays)


#: A walk's rows (scratch all NaN, coordinates, slots, window entries): a walk takes a set, the cast gives it back
#: once the combine has read its rows and made them NaN again.
_WALK_ROWS = _Spares(SPARE_ROWS_BYTES, 2)
#: A cast's cells and evidence, given back by a caller done with them (``give_back``).
_CAST_CELLS = _Spares(SPARE_CELLS_BYTES, 1)


def _walk_rows(block_cells: int) -> tuple[np.ndarray, ...]:
    kept = _WALK_ROWS.take(lambda rows: rows[0].shape[1] == block_cells)
    if kept is not None:
        return kept
    return (np.full((64, block_cells), np.nan, np.float32), np.empty((64, 3), np.int32), np.empty(64, np.int64),
            np.empty(64, np.int64))


def give_back(cast: CastResult) -> None:
    """The caller is done with ``cast`` (its cells are no longer read): its arrays may take the next cast's cells."""
    cells = cast.cells if cast.cells.base is None else cast.cells.base
    dist = cast.distance_sigmas if cast.distance_sigmas.base is None else cast.distance_sigmas.base
    if (isinstance(cells, np.ndarray) and isinstance(dist, np.ndarray) and cells.dtype == np.int64
            and dist.dtype == np.float32 and cells.ndim == dist.ndim == 1 and cells.shape == dist.shape):
        _CAST_CELLS.give((cells, dist))


@dataclass(frozen=True)
class Lattice:
    """The cells a cast numbers: cell ``i`` along axis ``a`` covers ``[lower[a] + i * resolution, lower[a] + (i + 1) *
    resolution)``. ``shape`` bounds a fixed map's box (``[0, shape)`` along each axis, rays clipped to it); None is the
    unbounded lattice of a growing map."""

    lower: tuple[float, ...]
    resolution: float
    shape: tuple[int, ...] | None

    @property
    def ndim(self) -> int:
        """2 or 3."""
        return len(self.lower)

    @classmethod
    def of(cls, spec: GridSpec) -> Lattice:
        """The lattice of a fixed map's box."""
        return cls(tuple(float(v) for v in spec.origin), float(spec.resolution), tuple(int(n) for n in spec.shape))


def _in_three(lattice: Lattice, origins: np.ndarray, directions: np.ndarray,
              t_end: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rays as the kernels walk them: checked (finite, of the lattice's dimension), in 3-D (a 2-D lattice is a 3-D
    one of a single layer, its rays in its mid-plane), stopped where an unbounded lattice's coordinates end; with
    the lattice's lower corner and shape in cells (0: unbounded along the axis, ``_axis_setup``)."""
    d = lattice.ndim
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    n_rays = origins.shape[0]
    if origins.shape != (n_rays, d) or directions.shape != (n_rays, d):
        raise ValueError(f"origins and directions must both have shape (R, {d}), got {origins.shape}, {directions.shape}")
    t_end = np.ascontiguousarray(t_end, dtype=np.float64)
    if not (np.isfinite(origins).all() and np.isfinite(directions).all() and np.isfinite(t_end).all()):
        # the kernel trusts them: a NaN direction made it hand out cell ids it never wrote (out of bounds)
        raise ValueError("origins, directions and t_end must be finite")
    lower = np.zeros(3)
    lower[:d] = lattice.lower
    shape = np.zeros(3, dtype=np.int64)
    if lattice.shape is not None:
        shape[:] = 1
        shape[:d] = lattice.shape
    else:
        # Stop every ray where it leaves the region whose cells have 32-bit block coordinates.
        with np.errstate(divide="ignore", invalid="ignore"):
            exit_t = np.where(directions == 0.0, np.inf, (np.sign(directions) * MAX_COORDINATE_M - origins) / directions)
        t_end = np.minimum(t_end, exit_t.min(axis=1))
    if d == 2:
        origins = np.concatenate([origins, np.full((n_rays, 1), lower[2] + 0.5 * lattice.resolution)], axis=1)
        directions = np.concatenate([directions, np.zeros((n_rays, 1))], axis=1)
    return np.ascontiguousarray(origins), np.ascontiguousarray(directions), t_end, lower, shape


def cast_into(
    lattice: Lattice,
    index: BlockIndex,
    shift: tuple[int, int, int],
    origins: np.ndarray,
    directions: np.ndarray,
    t_end: np.ndarray,
    measured: np.ndarray,
    sigma: np.ndarray,
    ray_offsets: np.ndarray,
    *,
    unknown_from: float,
    window_limit: int = WINDOW_LIMIT,
    reuse: bool = False,
    split: bool = True,
    enter: bool = True,
) -> CastResult:
    """Traverse the cells of every ray of a batch of scans and keep one evidence per (scan, cell).

    Cells are numbered by the blocks of ``index`` (``2**shift[a]`` cells along axis ``a``): the
    id of cell ``(i, j, k)`` is ``slot << sum(shift) | offset``, ``slot`` the index's slot of block
    ``(i >> sx, j >> sy, k >> sz)`` (added to the index if new) and ``offset`` the C-order index of
    ``(i & mx, j & my, k & mz)`` in it. A scan's cells come block by block.

    Parameters
    ----------
    lattice : Lattice
        The map's cells.
    index : BlockIndex
        The map's blocks; blocks the rays reach are added.
    shift : (3,) ints
        Block size, as powers of two (a 2-D lattice has one z layer: shift z 0).
    origins, directions, t_end, measured, sigma, ray_offsets, unknown_from
        As :func:`cast_rays`.
    split : bool
        Split the walks between threads (``fuzzyocc.parallel``) when the rays are many; False: one walk, for a cast
        cheap enough that ordering its rays for the split would cost more than it saves.
    reuse : bool
        Write the cells into arrays a cast gave back (:func:`give_back`) when there is one: for a caller that is done
        with each cast before the next, so that a lidar sweep's cells do not take fresh memory every sweep.
    enter : bool
        Enter the blocks the rays reach into ``index`` (True), or leave the index as it is and return them with
        the cast (``CastResult.new_blocks``), for a caller that casts while others read the map and enters them
        with :func:`enter_new_blocks` when it fuses.
    window_limit : int
        Most blocks of a scan's dense window (the blocks its rays span); a wider scan finds its blocks in the index's
        hash alone. The cells are the same either way.
    """
    origins, directions, t_end, lower, shape = _in_three(lattice, origins, directions, t_end)
    n_rays = origins.shape[0]
    offsets = np.asarray(ray_offsets, dtype=np.int64)
    if offsets.ndim != 1 or offsets.size < 1 or offsets[0] != 0 or offsets[-1] != n_rays or np.any(np.diff(offsets) < 0):
        raise ValueError("ray_offsets must rise from 0 to the number of rays")
    shifts = np.asarray(shift, dtype=np.int64)
    if shifts.shape != (3,) or np.any(shifts < 0) or np.any(shifts > 8) or (lattice.ndim == 2 and shifts[2] != 0):
        raise ValueError(f"shift must be 3 integers in [0, 8] (z 0 on a 2-D lattice), got {shift}")
    measured = np.asarray(measured, dtype=np.float64)
    no_return = np.isnan(measured)
    slope = np.where(no_return, 0.0, 1.0 / np.asarray(sigma, dtype=np.float64))
    args = (origins, directions, t_end, slope,
            np.where(no_return, NO_RETURN_DISTANCE, -measured * slope))
    rest = (lower, shape, float(lattice.resolution), float(unknown_from), shifts, index.keys, index.slots,
            int(window_limit), True if lattice.ndim == 2 else None, True if lattice.shape is not None else None)
    # Each walk takes a sector of azimuth of every scan (as many rays each, and few blocks in two walks: a lidar gives
    # its rays beam by beam, and the first half, its upward beams, reached a sixth of the blocks the second did). The
    # cells and their evidence do not depend on the split (a cell's evidence is a maximum), nor do the slots new
    # blocks get (``_new_blocks``).
    n_walks = parallel.walks_for(n_rays) if split else 1
    counts = np.diff(offsets)
    if n_walks > 1:
        azimuth = np.arctan2(args[1][:, 1], args[1][:, 0])
        order = np.concatenate([lo + np.argsort(azimuth[lo:hi], kind="stable")
                                for lo, hi in zip(offsets[:-1], offsets[1:])])
        args = tuple(a[order] for a in args)
    block_cells = 1 << int(shifts.sum())
    walks = parallel.run(lambda p: _walk(*args, offsets[:-1] + counts * p // n_walks,
                                         offsets[:-1] + counts * (p + 1) // n_walks, *rest,
                                         *_walk_rows(block_cells)), range(n_walks))
    rows = [int(w[3][-1]) for w in walks]
    rcoords, rslot = (np.concatenate([w[k][:n] for w, n in zip(walks, rows)]) for k in (1, 2))
    row_offsets = np.stack([w[3] for w in walks])
    traversed = np.sum([w[4] for w in walks], axis=0)
    new = _new_blocks(rcoords, rslot, rslot.shape[0])
    index_at = (index.n, index.dropped)
    if enter:
        _enter_all(index, new)
    else:
        _slot_new(rcoords, rslot, new, index.n)  # the slots ``_enter`` will give them
    out = (_CAST_CELLS.take(lambda _: True) if reuse else None) or (np.empty(0, np.int64), np.empty(0, np.float32))
    cells, dist, scan_offsets, n_out = _combine(tuple(w[0] for w in walks), rcoords, rslot, row_offsets,
                                                index.keys, index.slots, int(shifts.sum()),
                                                sum(int(w[6]) for w in walks), *out)
    cells, dist = cells[:n_out], dist[:n_out]  # views: a copy would double the peak
    for w in walks:
        _WALK_ROWS.give((*w[:3], w[5]))
    return CastResult(cells=cells, distance_sigmas=dist, scan_offsets=scan_offsets, cells_traversed=traversed,
                      new_blocks=None if enter else new, index_at=index_at)


@njit(cache=True, nogil=True)
def _crossed(origins, dirs, t_end, lower, shape, res, bounded, limit):  # pragma: no cover - compiled
    # The cells the rays cross, each once, by ``_walk``'s traversal (the same cells, the same ties), without the
    # evidence, the rows and their combine: a dense mark per cell of the box the rays' ends span, one cell more each
    # side (rounding). ``ok`` False, nothing done, when that box holds more than ``limit`` cells.
    nx, ny, nz = shape[0], shape[1], shape[2]
    big = np.int64(1) << 62
    lo_x, lo_y, lo_z, hi_x, hi_y, hi_z = big, big, big, -big, -big, -big
    for r in range(origins.shape[0]):
        t0, t1 = _clipped(origins, dirs, t_end, r, lower, shape, res, bounded)
        if not t0 < t1:
            continue
        for t in (t0, t1):
            bx = _block_at(origins[r, 0], dirs[r, 0], t, lower[0], nx, res, 0)
            by = _block_at(origins[r, 1], dirs[r, 1], t, lower[1], ny, res, 0)
            bz = _block_at(origins[r, 2], dirs[r, 2], t, lower[2], nz, res, 0)
            lo_x, lo_y, lo_z = min(lo_x, bx), min(lo_y, by), min(lo_z, bz)
            hi_x, hi_y, hi_z = max(hi_x, bx), max(hi_y, by), max(hi_z, bz)
    out = np.empty((0, 3), np.int32)
    if hi_x < lo_x:
        return out, True
    lo_x, lo_y, lo_z = lo_x - 1, lo_y - 1, lo_z - 1
    wx, wy, wz = hi_x - lo_x + 2, hi_y - lo_y + 2, hi_z - lo_z + 2
    if wx > limit or wy > limit or wz > limit or wx * wy > limit or wx * wy * wz > limit:
        return out, False
    seen = np.zeros(wx * wy * wz, np.uint8)
    out = np.empty((1024, 3), np.int32)
    m = 0
    for r in range(origins.shape[0]):
        t0, t1 = _clipped(origins, dirs, t_end, r, lower, shape, res, bounded)
        if not t0 < t1:
            continue
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        ix, sx, tmx, tdx, _ = _axis_setup(ox, dx, t0, lower[0], nx, res)
        iy, sy, tmy, tdy, _ = _axis_setup(oy, dy, t0, lower[1], ny, res)
        iz, sz, tmz, tdz, _ = _axis_setup(oz, dz, t0, lower[2], nz, res)
        while True:
            qx, qy, qz = ix - lo_x, iy - lo_y, iz - lo_z
            if not (_u(qx) < _u(wx) and _u(qy) < _u(wy) and _u(qz) < _u(wz)):
                return out[:0], False  # outside the box of the ends (never seen): the caller casts instead
            q = (qx * wy + qy) * wz + qz
            if seen[q] == 0:
                seen[q] = 1
                if m == out.shape[0]:
                    grown = np.empty((2 * m, 3), np.int32)
                    grown[:m] = out
                    out = grown
                out[m, 0], out[m, 1], out[m, 2] = ix, iy, iz
                m += 1
            if tmx <= tmy and tmx <= tmz:
                t_out, ax = tmx, 0
            elif tmy <= tmz:
                t_out, ax = tmy, 1
            else:
                t_out, ax = tmz, 2
            if t_out >= t1:
                break
            if ax == 0:
                ix += sx
                if bounded is not None and (ix < 0 or ix >= nx):
                    break
                tmx += tdx
            elif ax == 1:
                iy += sy
                if bounded is not None and (iy < 0 or iy >= ny):
                    break
                tmy += tdy
            else:
                iz += sz
                if bounded is not None and (iz < 0 or iz >= nz):
                    break
                tmz += tdz
    return out[:m], True


def cross_into(lattice: Lattice, index: BlockIndex, origins: np.ndarray, directions: np.ndarray,
               t_end: np.ndarray) -> None:
    """Enter into ``index`` every cell of ``lattice`` the rays cross that it lacks: :func:`cast_into`'s cells of
    ``shift`` 0, without their evidence (what a bound on the blocks a batch makes counts, ``maps.allocation_bound``),
    in no particular order of slots.

    The cells are marked in a dense array over the box of the rays' ends (a lidar sweep's at 0.4 m: 1-3 M cells,
    about 4x faster than the cast, whose rows and combine serve the evidence); rays spanning more than
    ``WINDOW_LIMIT`` cells are cast.
    """
    o, d, t, lower, shape = _in_three(lattice, origins, directions, t_end)
    cells, ok = _crossed(o, d, t, lower, shape, float(lattice.resolution),
                         True if lattice.shape is not None else None, WINDOW_LIMIT)
    if ok:
        _enter_all(index, cells[index.find(cells) < 0])
        return
    n = o.shape[0]
    cast_into(lattice, index, (0, 0, 0), origins, directions, t_end, np.full(n, np.nan), np.ones(n),
              np.array([0, n]), unknown_from=np.inf, split=False)


def fits(index: BlockIndex, cast: CastResult) -> bool:
    """Whether the slots ``cast``'s cells name are still those of ``index`` (the one it was made on)."""
    return (index.n, index.dropped) == cast.index_at


def enter_new_blocks(index: BlockIndex, cast: CastResult) -> None:
    """Enter the blocks of a cast made with ``enter=False`` into ``index``, at the slots its cells name.

    ``ValueError`` if the index changed since the cast (its slots would name other blocks): cast again."""
    if cast.new_blocks is None:
        return
    if not fits(index, cast):
        raise ValueError(f"the index holds {index.n} blocks ({index.dropped} dropped), the cast was made on "
                         f"{cast.index_at[0]} ({cast.index_at[1]}): cast again")
    _enter_all(index, cast.new_blocks)


def _enter_all(index: BlockIndex, blocks: np.ndarray) -> None:
    """Enter ``blocks`` (absent, in the order of :func:`_new_blocks`) at the index's next slots."""
    index.reserve(blocks.shape[0])
    index.n = _enter(blocks, index.keys, index.slots, index.coords, index.n)


def flat_ids(keys: np.ndarray, index: BlockIndex, shift: tuple[int, int, int], shape: tuple[int, ...]) -> np.ndarray:
    """The flat ids (C order over a fixed box of ``shape`` cells) of the cells of :func:`cast_into`'s ``keys``."""
    full = np.ones(3, dtype=np.int64)
    full[: len(shape)] = shape
    return _flat_ids(np.ascontiguousarray(keys, dtype=np.int64), index.coords, np.asarray(shift, dtype=np.int64), full)


@njit(cache=True, nogil=True)
def _flat_ids(keys, coords, shift, shape):  # pragma: no cover - compiled
    # one pass: the same in numpy took a quarter of a BayesMap's 2-D integrate (five temporaries of the batch's size)
    hx, hy, hz = shift[0], shift[1], shift[2]
    bits = hx + hy + hz
    out = np.empty(keys.shape[0], np.int64)
    for n in range(keys.shape[0]):
        slot = keys[n] >> bits
        o = keys[n] & ((1 << bits) - 1)
        i = (np.int64(coords[slot, 0]) << hx) + (o >> (hy + hz))
        j = (np.int64(coords[slot, 1]) << hy) + ((o >> hz) & ((1 << hy) - 1))
        k = (np.int64(coords[slot, 2]) << hz) + (o & ((1 << hz) - 1))
        out[n] = (i * shape[1] + j) * shape[2] + k
    return out


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
) -> CastResult:
    """Traverse the cells of every ray of a batch of scans and keep one evidence per (scan, cell), as flat ids.

    The reference form of :func:`cast_into` for a fixed map's box: cells numbered by flat id
    (C order over ``spec.shape``), in increasing order within a scan.

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

    Returns
    -------
    CastResult
    """
    index = BlockIndex()
    cast = cast_into(Lattice.of(spec), index, (0, 0, 0), origins, directions, t_end, measured, sigma, ray_offsets,
                     unknown_from=unknown_from)
    cells = flat_ids(cast.cells, index, (0, 0, 0), spec.shape)
    # by scan, then by id
    scan = np.repeat(np.arange(cast.scan_offsets.size - 1), np.diff(cast.scan_offsets))
    order = np.lexsort((cells, scan))
    return CastResult(cells=cells[order], distance_sigmas=cast.distance_sigmas[order],
                      scan_offsets=cast.scan_offsets, cells_traversed=cast.cells_traversed)


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


def traversal_cells(spec: GridSpec | LatticeSpec, origin: np.ndarray, ends: np.ndarray) -> int:
    """About how many cells a cast walks for the segments ``origin`` -> each of ``ends`` ((N, D), metres).

    Each segment is clipped to the map's box (the cast never walks outside it), and walks one
    cell per cell boundary it crosses: its L1 length in cells, plus its first cell. A bound
    known before any cell is touched, for refusing work that is too large (the band a cast
    walks past a hit adds a few cells a ray, not counted). Compiled and without the GIL: the
    service estimates every batch before it is stored, refused ones too.
    """
    origin = np.ascontiguousarray(origin, dtype=np.float64).reshape(-1)
    ends = np.ascontiguousarray(ends, dtype=np.float64).reshape(-1, origin.size)
    if isinstance(spec, LatticeSpec):  # a growing map's rays stop where its lattice does (``cast_into``)
        lower, upper = np.full(spec.ndim, -MAX_COORDINATE_M), np.full(spec.ndim, MAX_COORDINATE_M)
    else:
        lower = np.asarray(spec.origin, dtype=np.float64)
        upper = lower + np.asarray(spec.shape, dtype=np.float64) * spec.resolution
    return int(_traversal_kernel(origin, ends, lower, upper, float(spec.resolution)))
