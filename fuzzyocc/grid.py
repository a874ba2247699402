"""Cell storage of a map: per-cell state, observed bits and a lazily refreshed fixed-point risk
cache; and the fuzzy fusion that writes into block storage.

A grid knows nothing of sensors: its map casts the rays and gives the function that turns
states into risk. Into a :class:`CellGrid` the map writes whole states (Bayes log-odds); a
:class:`BlockGrid` fuzzifies and fuses a scan's cells where they are stored (:meth:`BlockGrid.fuse`,
with the engine's compiled row kernels), because each fused row decides whether its uniform
block must be expanded or can stay uniform.

:class:`CellGrid` is dense, cells addressed by flat id (C order over ``spec.shape``, see
:mod:`fuzzyocc.keys`). Bytes per cell: the state's (4 for float32 log-odds) is the map
itself; besides it the grid keeps 1 bit (observed) and 2 bytes (risk cache, whose
all-ones value also marks a cell whose risk is stale, so no dirty mask is needed).

:class:`BlockGrid` stores rows of uint8 (the fuzzy engine's activations) by power-of-two
blocks, a block whose cells all hold one row keeping it once (OctoMap's pruning, on a
fixed two-level layout as in Bonxai); the risk cache is kept the same way.

Risk is cached as uint16 fixed point, ``risk = q / 2**16``: every cached risk is a multiple
of :data:`RISK_STEP` (2**-16), the nearest one to the model's value (ties to even), and
reading it back as float32 is exact. 0 and 0.5 (unknown) are represented exactly. The
largest value is ``65534 / 65536`` (1 - 3e-5); no model here gives a risk above it (the
fuzzy centroid stays 1/(3 (L - 1)) from 1, Bayes is clamped at 0.971).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import njit

from fuzzyocc._block_ids import block_address, cell_id
from fuzzyocc._engine_kernels import SLOPED, evidence_class, fuse_row, fuzzify_into
from fuzzyocc.config import GridSpec
from fuzzyocc.engine import Fuzzifier

RiskFn = Callable[[np.ndarray], np.ndarray]
#: What :meth:`fuzzyocc.engine.FuzzyEngine.row_fusion` returns.
RowFusion = tuple[np.ndarray, tuple[bool, bool, bool] | None]

#: Resolution of the cached risk: risk is read back as a multiple of this (2**-16).
RISK_STEP = 2.0**-16
#: Entries of a table indexed by risk code (``OccupancyMap.plane_lookup``): every uint16 value.
RISK_CODES = 1 << 16
_STALE = 0xFFFF  # a risk code no risk quantizes to: "recompute this cell"
_LARGEST_CODE = _STALE - 1


def quantize_risk(risk: np.ndarray) -> np.ndarray:
    """Risk in [0, 1] -> uint16 codes ``round(risk / RISK_STEP)`` (ties to even), at most 65534."""
    scaled = np.rint(np.asarray(risk, dtype=np.float64) * (1.0 / RISK_STEP))
    return np.clip(scaled, 0.0, _LARGEST_CODE).astype(np.uint16)


def dequantize_risk(codes: np.ndarray) -> np.ndarray:
    """uint16 codes -> float32 risk ``code * RISK_STEP`` (exact: codes fit float32's mantissa)."""
    out = np.asarray(codes).astype(np.float32)
    out *= np.float32(RISK_STEP)
    return out


class CellGrid:
    """State of every cell of a bounded 2-D or 3-D grid.

    Cells are addressed by flat id everywhere (:attr:`block_shift` is None).

    Parameters
    ----------
    spec : GridSpec
        The grid.
    state : (num_cells, ...) ndarray
        Initial state of every cell (taken over, not copied).
    observed : (num_cells,) ndarray of bool
        Cells some beam reached (packed into bits).
    risk_fn : callable
        ``(n, ...) states -> (n,) risk``; applied to the cells that changed when risk is read.
        A cell's cached risk depends on its state alone (quantized as in :func:`quantize_risk`),
        never on when it was refreshed.
    """

    #: Layout of the cell ids ``mark_observed`` and ``write`` take: flat.
    block_shift: tuple[int, int, int] | None = None

    def __init__(self, spec: GridSpec, state: np.ndarray, observed: np.ndarray, risk_fn: RiskFn) -> None:
        n = spec.num_cells
        if state.shape[:1] != (n,) or observed.shape != (n,) or observed.dtype != np.bool_:
            raise ValueError(f"state and observed must have {n} rows (one per cell)")
        self.spec = spec
        self.state = state
        self._observed = np.packbits(observed, bitorder="little")
        self._risk_fn = risk_fn
        self._risk = np.full(n, _STALE, dtype=np.uint16)
        self._any_stale = n > 0
        if n and self._uniform(state):
            # A fresh map: one evaluation instead of num_cells.
            self._risk[:] = quantize_risk(risk_fn(state[:1]))[0]
            self._any_stale = False

    @staticmethod
    def _uniform(state: np.ndarray) -> bool:
        # Byte for byte (equal bytes are equal states), without a temporary the size of the state.
        rows = np.ascontiguousarray(state).view(np.uint8).reshape(state.shape[0], -1)
        return bool(_rows_equal_first(rows))

    def ids(self, cells: np.ndarray) -> np.ndarray:
        """The ids of ``cells`` (flat ids) as :meth:`write` and :meth:`mark_observed` take them: the same."""
        return np.asarray(cells, dtype=np.int64)

    # -- states ---------------------------------------------------------------------------
    def read(self, cells: np.ndarray) -> np.ndarray:
        """States of ``cells`` (flat ids), a copy of shape ``(len(cells), ...)``."""
        if self.state.ndim == 2:
            return _gather_rows(self.state, cells)
        return self.state[cells]

    def write(self, cells: np.ndarray, new_state: np.ndarray) -> None:
        """Set the state of ``cells`` (flat ids, unique) and mark their risk stale."""
        if self.state.ndim == 2:
            _scatter_rows(self.state, cells, np.ascontiguousarray(new_state, dtype=self.state.dtype))
        else:
            self.state[cells] = new_state
        self.mark_changed(cells)

    def mark_changed(self, cells: np.ndarray) -> None:
        """Mark the risk of ``cells`` stale after their rows of :attr:`state` were changed in place."""
        _mark_stale(self._risk, cells)
        self._any_stale = self._any_stale or cells.size > 0

    # -- observed -------------------------------------------------------------------------
    def mark_observed(self, cells: np.ndarray) -> None:
        """Record that beams reached ``cells`` (flat ids)."""
        _set_bits(self._observed, cells)

    def observed(self) -> np.ndarray:
        """(num_cells,) bool: cells some beam reached (a new array)."""
        bits = np.unpackbits(self._observed, count=self.spec.num_cells, bitorder="little")
        return bits.view(np.bool_)

    # -- risk -----------------------------------------------------------------------------
    def _refresh(self) -> None:
        if self._any_stale:
            stale = np.flatnonzero(self._risk == _STALE)
            if stale.size:
                self._risk[stale] = quantize_risk(self._risk_fn(self.read(stale)))
            self._any_stale = False

    def risk(self) -> np.ndarray:
        """(num_cells,) float32 risk, a new array; the cache is refreshed first where cells changed."""
        self._refresh()
        return dequantize_risk(self._risk)

    def plane_lookup(self, lut: np.ndarray, unobserved: int) -> np.ndarray:
        """A 2-D grid's cells as (ny, nx) int8: ``lut[code]`` of each cell's risk code, ``unobserved`` where no beam
        reached; rows along y (an image's, or ``nav_msgs/OccupancyGrid``'s, order). One pass, no float copy."""
        self._refresh()
        nx, ny = self.spec.shape[:2]
        out = np.empty((ny, nx), dtype=np.int8)
        _lookup_flat(nx, ny, self._risk, self._observed, _check_lut(lut), np.int8(unobserved), out)
        return out

    def risk_of(self, cells: np.ndarray) -> np.ndarray:
        """(len(cells),) float32 risk of ``cells`` (flat ids), as :meth:`risk` gives it."""
        self._refresh()
        return dequantize_risk(self._risk[cells])

    # -- memory ---------------------------------------------------------------------------
    def persistent_nbytes(self) -> int:
        """Bytes of what the map is: cell states and observed bits (what ``to_arrays`` saves, packed)."""
        return int(self.state.nbytes + self._observed.nbytes)

    def resident_nbytes(self) -> int:
        """Bytes the grid holds between calls: :meth:`persistent_nbytes` plus the risk cache."""
        return self.persistent_nbytes() + int(self._risk.nbytes)


# numpy's fancy indexing of short rows (7 bytes a cell) costs far more than the copy itself.
@njit(cache=True, nogil=True)
def _gather_rows(state, cells):  # pragma: no cover - compiled
    out = np.empty((cells.shape[0], state.shape[1]), state.dtype)
    for n in range(cells.shape[0]):
        c = cells[n]
        for k in range(state.shape[1]):
            out[n, k] = state[c, k]
    return out


@njit(cache=True, nogil=True)
def _scatter_rows(state, cells, rows):  # pragma: no cover - compiled
    for n in range(cells.shape[0]):
        c = cells[n]
        for k in range(state.shape[1]):
            state[c, k] = rows[n, k]


@njit(cache=True, nogil=True)
def _rows_equal_first(rows):  # pragma: no cover - compiled
    for n in range(1, rows.shape[0]):
        for k in range(rows.shape[1]):
            if rows[n, k] != rows[0, k]:
                return False
    return True


@njit(cache=True, nogil=True)
def _mark_stale(codes, cells):  # pragma: no cover - compiled
    for n in range(cells.shape[0]):
        codes[cells[n]] = _STALE


@njit(cache=True, nogil=True)
def _set_bits(bits, cells):  # pragma: no cover - compiled
    # Little bit order (np.packbits(..., bitorder="little")): cell c is bit c % 8 of byte c // 8.
    for n in range(cells.shape[0]):
        c = cells[n]
        bits[c >> 3] |= np.uint8(1 << (c & 7))


# ------------------------------------------------------------------ uniform-block storage
#: Cells a block holds: 4 x 4 x 4 in 3-D, 4 x 4 in 2-D (a 2-D grid is one layer thick). On the
#: 2-D bench scene 4 x 4 fused as fast as 8 x 8, with the same state and a third less resident.
BLOCK_SHIFT_3D = 2
BLOCK_SHIFT_2D = 2


class BlockGrid:
    """Per-cell rows of uint8 (fuzzy activations) stored by uniform blocks, as OctoMap prunes.

    The grid is cut into power-of-two blocks (4 x 4 x 4 cells in 3-D, 4 x 4 in 2-D, narrower
    along an axis the grid is thinner than that; addressed by shifts and masks; edge blocks
    are padded past the grid). A block whose cells all hold the same row keeps that row once; any other block is a dense slab of rows in a pool. A
    scan expands the uniform blocks it changes, fuses, and collapses the blocks it changed
    that came out uniform; the pool stays packed (a freed slab takes the last one), so the
    map holds about ``rows * (fraction of non-uniform blocks)`` plus a few bytes a block.

    Cells are addressed by block id (:attr:`block_shift`, as
    :func:`fuzzyocc.raycast.cast_rays` numbers them with it) in :meth:`fuse` and
    :meth:`mark_observed`, so a scan's cells come grouped by block; by flat id in
    :meth:`risk_of`.

    What a row means is the caller's: rows are compared byte for byte, and a cell's risk
    (cached as in :class:`CellGrid`, uint16 per cell of a dense block, one per uniform block)
    depends on its row alone, so storage never changes a state or a risk.

    Parameters
    ----------
    spec : GridSpec
        The grid.
    width : int
        Bytes of one row (L labels).
    risk_fn : callable
        ``(n, L) rows -> (n,) risk``.
    """

    def __init__(self, spec: GridSpec, width: int, risk_fn: RiskFn) -> None:
        self.spec = spec
        self._risk_fn = risk_fn
        d = spec.ndim
        shape = np.ones(3, dtype=np.int64)
        shape[:d] = spec.shape
        s = BLOCK_SHIFT_3D if d == 3 else BLOCK_SHIFT_2D
        self._shape = shape
        # No wider than the grid along an axis (a 3-D map 1 or 2 cells thick is not padded to 4).
        self._shift = np.array([min(s, (int(n) - 1).bit_length()) for n in shape], dtype=np.int64)
        sx, sy, sz = (int(v) for v in self._shift)
        self.block_shift: tuple[int, int, int] | None = (sx, sy, sz)
        self._bits = int(self._shift.sum())
        self._nblk = (shape + (1 << self._shift) - 1) >> self._shift  # blocks along each axis
        n_blocks = int(np.prod(self._nblk))
        self._block_cells = 1 << int(self._shift.sum())
        self._width = int(width)
        self._ref = np.full(n_blocks, -1, dtype=np.int32)  # pool slot of a dense block, -1 = uniform
        self._urow = np.zeros((n_blocks, width), dtype=np.uint8)  # the row of a uniform block
        self._urisk = np.full(n_blocks, _STALE, dtype=np.uint16)
        self._n_dense = 0
        self._alloc_pool(0)
        self._observed = np.zeros(((n_blocks << self._bits) + 7) // 8, dtype=np.uint8)  # by block id
        self._any_stale = True

    def _alloc_pool(self, capacity: int) -> None:
        pool = np.empty((capacity, self._block_cells, self._width), dtype=np.uint8)
        prisk = np.empty((capacity, self._block_cells), dtype=np.uint16)
        owner = np.empty(capacity, dtype=np.int32)  # block of each slot, to move a slab
        n = self._n_dense
        if n:
            pool[:n] = self._pool[:n]
            prisk[:n] = self._prisk[:n]
            owner[:n] = self._owner[:n]
        self._pool, self._prisk, self._owner = pool, prisk, owner

    def _grow(self, capacity: int) -> None:
        self._alloc_pool(max(capacity, self._n_dense))

    @classmethod
    def filled(cls, spec: GridSpec, row: np.ndarray, risk_fn: RiskFn) -> BlockGrid:
        """Every cell holding ``row`` ((L,) uint8), none observed."""
        row = np.ascontiguousarray(row, dtype=np.uint8).reshape(-1)
        grid = cls(spec, row.size, risk_fn)
        grid._urow[:] = row
        grid._urisk[:] = quantize_risk(risk_fn(row[None, :]))[0]
        grid._any_stale = False
        return grid

    @classmethod
    def from_dense(cls, spec: GridSpec, state: np.ndarray, observed: np.ndarray, risk_fn: RiskFn) -> BlockGrid:
        """Compress ``state`` ((num_cells, L) uint8, C order over ``spec.shape``) and ``observed``."""
        n = spec.num_cells
        if state.ndim != 2 or state.shape[0] != n or state.dtype != np.uint8:
            raise ValueError(f"state must be uint8 of shape ({n}, L) (one row per cell)")
        if observed.shape != (n,) or observed.dtype != np.bool_:
            raise ValueError(f"observed must be bool of shape ({n},)")
        state = np.ascontiguousarray(state)
        grid = cls(spec, state.shape[1], risk_fn)
        n_dense = _find_uniform(state, grid._shape, grid._shift, grid._nblk, grid._urow, grid._ref)
        grid._grow(n_dense)
        grid._n_dense = _fill_dense(state, grid._shape, grid._shift, grid._nblk, grid._urow, grid._ref,
                                    grid._pool, grid._owner)
        grid._prisk[:n_dense] = _STALE
        _set_bits(grid._observed, grid.ids(np.flatnonzero(observed)))
        return grid

    def ids(self, cells: np.ndarray) -> np.ndarray:
        """The block ids of ``cells`` (flat ids), as :meth:`fuse` and :meth:`mark_observed` take them."""
        blk, off = self._locate(cells)
        return (blk << self._bits) | off

    # -- states ---------------------------------------------------------------------------
    def _locate(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _block_of(np.ascontiguousarray(cells, dtype=np.int64), self._shape, self._shift, self._nblk)

    def read(self, cells: np.ndarray) -> np.ndarray:
        """Rows of ``cells`` (flat ids), a new ``(len(cells), L)`` array."""
        blk, off = self._locate(cells)
        return _gather_blocks(blk, off, self._ref, self._urow, self._pool)

    def dense(self) -> np.ndarray:
        """Every cell's row, a new ``(num_cells, L)`` array in C order over ``spec.shape``."""
        out = np.empty((self.spec.num_cells, self._width), dtype=np.uint8)
        _expand_rows(self._shape, self._shift, self._nblk, self._ref, self._urow, self._pool, out)
        return out

    def fuse(self, cells: np.ndarray, distance_sigmas: np.ndarray, fuzzifier: Fuzzifier,
             row_fusion: RowFusion) -> None:
        """Fuse the evidence at ``distance_sigmas`` ((n,) float, no NaN) into the rows of ``cells``
        (block ids, unique, increasing).

        ``fuzzifier`` is :meth:`fuzzyocc.engine.FuzzyEngine.fuzzifier` and ``row_fusion``
        :meth:`fuzzyocc.engine.FuzzyEngine.row_fusion`: each row becomes what
        ``engine.fuse(row, engine.fuzzify(distance))`` gives for it, computed in place without
        an (n, L) evidence array. Uniform blocks a changed cell lies in are expanded first;
        changed blocks that came out uniform are collapsed after.
        """
        if cells.size == 0:
            return
        keys = np.ascontiguousarray(cells, dtype=np.int64)
        if distance_sigmas.shape != keys.shape:
            raise ValueError(f"distance_sigmas must have shape {keys.shape}, got {distance_sigmas.shape}")
        rules, float_ops = row_fusion
        touched = np.empty(keys.size, dtype=np.int64)
        start = n_touched = 0
        while True:  # the pool grows only when a uniform block must be expanded and no slot is left
            start, self._n_dense, n_touched = _fuse_write(
                keys, self._bits, distance_sigmas, *fuzzifier, rules, float_ops, start, touched,
                n_touched, self._ref, self._urow, self._urisk, self._pool.reshape(-1, self._width), self._prisk,
                self._owner, self._n_dense)
            if start == keys.size:
                break
            self._grow(self._n_dense + max(64, self._n_dense // 2))
        if n_touched == 0:
            return
        self._n_dense = _collapse(touched[:n_touched], self._shape, self._shift, self._nblk, self._ref,
                                  self._urow, self._urisk, self._pool, self._prisk, self._owner, self._n_dense)
        if 2 * self._n_dense < self._pool.shape[0] and self._pool.shape[0] > 64:  # give the slack back
            self._grow(self._n_dense + self._n_dense // 4)
        self._any_stale = True

    # -- observed -------------------------------------------------------------------------
    def mark_observed(self, cells: np.ndarray) -> None:
        """Record that beams reached ``cells`` (block ids)."""
        _set_bits(self._observed, cells)

    def observed(self) -> np.ndarray:
        """(num_cells,) bool in flat order: cells some beam reached (a new array)."""
        out = np.empty(self.spec.num_cells, dtype=np.bool_)
        _expand_bits(self._shape, self._shift, self._nblk, self._observed, out)
        return out

    # -- risk -----------------------------------------------------------------------------
    def _refresh(self) -> None:
        if not self._any_stale:
            return
        codes = self._prisk[: self._n_dense].reshape(-1)
        stale = np.flatnonzero(codes == _STALE)
        if stale.size:  # padding rows past the grid's edge hold a real row too: harmless to refresh
            codes[stale] = quantize_risk(self._risk_fn(self._pool[: self._n_dense].reshape(-1, self._width)[stale]))
        stale = np.flatnonzero((self._urisk == _STALE) & (self._ref < 0))
        if stale.size:
            self._urisk[stale] = quantize_risk(self._risk_fn(self._urow[stale]))
        self._any_stale = False

    def risk(self) -> np.ndarray:
        """(num_cells,) float32 risk, a new array; the cache is refreshed first where cells changed."""
        self._refresh()
        out = np.empty(self.spec.num_cells, dtype=np.float32)
        _expand_risk(self._shape, self._shift, self._nblk, self._ref, self._urisk, self._prisk, out)
        return out

    def plane_lookup(self, lut: np.ndarray, unobserved: int) -> np.ndarray:
        """As :meth:`CellGrid.plane_lookup`."""
        self._refresh()
        nx, ny = self.spec.shape[:2]
        out = np.empty((ny, nx), dtype=np.int8)
        _lookup_blocks(self._shape, self._shift, self._nblk, self._ref, self._urisk, self._prisk, self._observed,
                       _check_lut(lut), np.int8(unobserved), out)
        return out

    def risk_of(self, cells: np.ndarray) -> np.ndarray:
        """(len(cells),) float32 risk of ``cells`` (flat ids), as :meth:`risk` gives it."""
        self._refresh()
        blk, off = self._locate(cells)
        return dequantize_risk(_gather_codes(blk, off, self._ref, self._urisk, self._prisk))

    # -- memory ---------------------------------------------------------------------------
    def persistent_nbytes(self) -> int:
        """Bytes of what the map is: dense slabs in use, block table and rows, observed bits."""
        slabs = self._n_dense * self._block_cells * self._width
        return int(slabs + self._ref.nbytes + self._urow.nbytes + self._observed.nbytes)

    def resident_nbytes(self) -> int:
        """Bytes held between calls: the whole pool (spare slots too), risk caches, block tables."""
        arrays = (self._ref, self._urow, self._urisk, self._observed, self._pool, self._prisk,
                  self._owner)
        return int(sum(a.nbytes for a in arrays))


@njit(cache=True, nogil=True)
def _block_of(cells, shape, shift, nblk):  # pragma: no cover - compiled
    """Block id and offset in the block of each flat cell id."""
    ny, nz = shape[1], shape[2]
    sx, sy, sz = shift[0], shift[1], shift[2]
    nby, nbz = nblk[1], nblk[2]
    blk = np.empty(cells.shape[0], np.int64)
    off = np.empty(cells.shape[0], np.int64)
    for n in range(cells.shape[0]):
        c = cells[n]
        i = c // (ny * nz)
        r = c - i * (ny * nz)
        j = r // nz
        k = r - j * nz
        blk[n], off[n] = block_address(i, j, k, sx, sy, sz, nby, nbz)
    return blk, off


@njit(cache=True, nogil=True)
def _gather_blocks(blk, off, ref, urow, pool):  # pragma: no cover - compiled
    width = urow.shape[1]
    out = np.empty((blk.shape[0], width), np.uint8)
    for n in range(blk.shape[0]):
        s = ref[blk[n]]
        if s < 0:
            for k in range(width):
                out[n, k] = urow[blk[n], k]
        else:
            for k in range(width):
                out[n, k] = pool[s, off[n], k]
    return out


@njit(cache=True, nogil=True)
def _gather_codes(blk, off, ref, urisk, prisk):  # pragma: no cover - compiled
    out = np.empty(blk.shape[0], np.uint16)
    for n in range(blk.shape[0]):
        s = ref[blk[n]]
        out[n] = urisk[blk[n]] if s < 0 else prisk[s, off[n]]
    return out


@njit(cache=True, nogil=True, inline="always")
def _same_row(row, table, i):  # pragma: no cover - compiled
    """Whether ``row`` equals ``table[i]`` byte for byte."""
    for k in range(row.shape[0]):
        if row[k] != table[i, k]:
            return False
    return True


@njit(cache=True, nogil=True)
def _fuse_write(keys, bits, distances, xs, ys, counts, const_rows, bounds, rules, float_ops, start, touched,
                n_touched, ref, urow, urisk, rows, prisk, owner, n_dense):  # pragma: no cover - compiled
    """Fuse from cell ``start`` on, writing the rows that change and expanding their uniform blocks.

    ``rows`` is the pool as (slots * block cells, L). Fused cells of dense blocks and changed
    cells of uniform ones are written, their risk goes stale and their blocks are appended
    to ``touched`` once each (keys rise). A uniform block all of whose cells come with the
    same constant evidence is fused once, as a block, and stays uniform. Stops early, returning the cell
    to resume from, when a block needs a slot and the pool is full; nothing of that cell is
    written then. Returns ``(next cell, dense blocks, touched blocks)``.
    """
    width = urow.shape[1]
    mask = (1 << bits) - 1
    block_cells = prisk.shape[1]
    capacity = prisk.shape[0]
    out = np.empty(width, np.uint8)
    acc = np.zeros(width)
    active = np.empty(width, np.int64)
    # The evidence rows: the engine's constant ones by class, and the sloped one, fuzzified here
    # (an (n, L) array of them cost more to write and read back than the fusion itself).
    evidence = np.empty((SLOPED + 1, width), np.uint8)
    for c in range(SLOPED):
        for k in range(width):
            evidence[c, k] = const_rows[c, k]
    # A uniform block's cells come one after another (keys rise) and most carry the same constant
    # evidence (free space far in front of the surface): once a row left the block's row
    # unchanged, the next cell of that block in the same class is skipped without fusing it again.
    noop_block = -1
    noop_class = -1
    n = start - 1
    while n + 1 < keys.shape[0]:
        n += 1
        v = distances[n]
        e = evidence_class(v, bounds)
        if e == SLOPED:
            fuzzify_into(v, xs, ys, counts, evidence, e)
        b = keys[n] >> bits
        o = keys[n] & mask
        s = ref[b]
        if s < 0:
            if b == noop_block and e == noop_class:
                continue
            if e != SLOPED and n + block_cells <= keys.shape[0] and keys[n + block_cells - 1] >> bits == b:
                # Every cell of the block is here (keys are unique and rise). If all take this constant
                # evidence the block stays uniform, with the fused row: it is neither expanded, fused
                # cell by cell, nor collapsed (in front of a robot whole blocks step from one free
                # level to the next together).
                whole = True
                for q in range(n + 1, n + block_cells):
                    if evidence_class(distances[q], bounds) != e:
                        whole = False
                        break
                if whole:
                    fuse_row(urow, b, evidence, e, rules, float_ops, out, acc, active)
                    if not _same_row(out, urow, b):
                        for k in range(width):
                            urow[b, k] = out[k]
                        urisk[b] = _STALE
                        touched[n_touched] = b  # read by nothing but the stale flag: collapse skips it
                        n_touched += 1
                    n += block_cells - 1
                    continue
            fuse_row(urow, b, evidence, e, rules, float_ops, out, acc, active)
            if _same_row(out, urow, b):
                if e != SLOPED:  # a sloped row differs from cell to cell
                    noop_block = b
                    noop_class = e
                continue
            if n_dense == capacity:
                return n, n_dense, n_touched
            s = n_dense
            n_dense += 1
            ref[b] = s
            owner[s] = b
            base = s * block_cells
            for q in range(block_cells):
                for k in range(width):
                    rows[base + q, k] = urow[b, k]
                prisk[s, q] = urisk[b]
        else:
            # Written back whether it changed or not: a compare here mispredicts more than it saves.
            fuse_row(rows, s * block_cells + o, evidence, e, rules, float_ops, out, acc, active)
        c = s * block_cells + o
        for k in range(width):
            rows[c, k] = out[k]
        prisk[s, o] = _STALE
        if n_touched == 0 or touched[n_touched - 1] != b:
            touched[n_touched] = b
            n_touched += 1
    return keys.shape[0], n_dense, n_touched


@njit(cache=True, nogil=True, inline="always")
def _extent(b, shape, shift, nblk):  # pragma: no cover - compiled
    """Cells of block ``b`` inside the grid along each axis (edge blocks are cut by the grid)."""
    bz = b % nblk[2]
    by = (b // nblk[2]) % nblk[1]
    bx = b // (nblk[2] * nblk[1])
    ex = min(1 << shift[0], shape[0] - (bx << shift[0]))
    ey = min(1 << shift[1], shape[1] - (by << shift[1]))
    ez = min(1 << shift[2], shape[2] - (bz << shift[2]))
    return bx, by, bz, ex, ey, ez


@njit(cache=True, nogil=True)
def _slab_uniform(slab, ex, ey, ez, sy, sz):  # pragma: no cover - compiled
    """Whether the in-grid rows of a dense slab are all equal (to its row 0, always in the grid)."""
    width = slab.shape[1]
    for lx in range(ex):
        for ly in range(ey):
            base = (lx << sy | ly) << sz
            for lz in range(ez):
                o = base | lz
                for k in range(width):
                    if slab[o, k] != slab[0, k]:
                        return False
    return True


@njit(cache=True, nogil=True)
def _collapse(touched, shape, shift, nblk, ref, urow, urisk, pool, prisk, owner, n_dense):  # pragma: no cover
    """Collapse the ``touched`` blocks that became uniform; returns the dense count (pool kept packed)."""
    width = pool.shape[2]
    for t in range(touched.shape[0]):
        b = touched[t]
        s = ref[b]
        if s < 0:  # listed twice (keys out of order) and collapsed already
            continue
        _, _, _, ex, ey, ez = _extent(b, shape, shift, nblk)
        if not _slab_uniform(pool[s], ex, ey, ez, shift[1], shift[2]):
            continue
        for k in range(width):
            urow[b, k] = pool[s, 0, k]
        # All in-grid cells hold one row, so any fresh code among them is the block's.
        code = _STALE
        for lx in range(ex):
            for ly in range(ey):
                base = (lx << shift[1] | ly) << shift[2]
                for lz in range(ez):
                    if prisk[s, base | lz] != _STALE:
                        code = prisk[s, base | lz]
        urisk[b] = code
        ref[b] = -1
        last = n_dense - 1  # keep the pool packed: the last slab moves into the hole
        if s != last:
            # element by element: a slice assignment would compile numba's shape-mismatch error
            # message formatting into this kernel (seconds more at the first start, on a cold cache)
            for o in range(pool.shape[1]):
                for k in range(width):
                    pool[s, o, k] = pool[last, o, k]
            for o in range(prisk.shape[1]):
                prisk[s, o] = prisk[last, o]
            moved = owner[last]
            owner[s] = moved
            ref[moved] = s
        n_dense = last
    return n_dense


@njit(cache=True, nogil=True)
def _find_uniform(state, shape, shift, nblk, urow, ref):  # pragma: no cover - compiled
    """Mark each block uniform (its row in ``urow``) or dense (``ref`` 0); returns how many are dense."""
    width = state.shape[1]
    ny, nz = shape[1], shape[2]
    n_dense = 0
    for b in range(ref.shape[0]):
        bx, by, bz, ex, ey, ez = _extent(b, shape, shift, nblk)
        first = ((bx << shift[0]) * ny + (by << shift[1])) * nz + (bz << shift[2])
        uniform = True
        for lx in range(ex):
            for ly in range(ey):
                row0 = (((bx << shift[0]) + lx) * ny + (by << shift[1]) + ly) * nz + (bz << shift[2])
                for lz in range(ez):
                    for k in range(width):
                        if state[row0 + lz, k] != state[first, k]:
                            uniform = False
        if uniform:
            ref[b] = -1
            for k in range(width):
                urow[b, k] = state[first, k]
        else:
            ref[b] = 0
            n_dense += 1
    return n_dense


@njit(cache=True, nogil=True)
def _fill_dense(state, shape, shift, nblk, urow, ref, pool, owner):  # pragma: no cover - compiled
    """Copy the blocks ``_find_uniform`` left dense into the pool (padding: the block's first row)."""
    width = state.shape[1]
    ny, nz = shape[1], shape[2]
    n_dense = 0
    for b in range(ref.shape[0]):
        if ref[b] < 0:
            continue
        s = n_dense
        n_dense += 1
        ref[b] = s
        owner[s] = b
        bx, by, bz, ex, ey, ez = _extent(b, shape, shift, nblk)
        first = ((bx << shift[0]) * ny + (by << shift[1])) * nz + (bz << shift[2])
        for o in range(pool.shape[1]):
            for k in range(width):
                pool[s, o, k] = state[first, k]
        for lx in range(ex):
            for ly in range(ey):
                row0 = (((bx << shift[0]) + lx) * ny + (by << shift[1]) + ly) * nz + (bz << shift[2])
                for lz in range(ez):
                    o = (lx << shift[1] | ly) << shift[2] | lz
                    for k in range(width):
                        pool[s, o, k] = state[row0 + lz, k]
    return n_dense


@njit(cache=True, nogil=True)
def _expand_rows(shape, shift, nblk, ref, urow, pool, out):  # pragma: no cover - compiled
    width = urow.shape[1]
    nx, ny, nz = shape[0], shape[1], shape[2]
    sx, sy, sz = shift[0], shift[1], shift[2]
    nby, nbz = nblk[1], nblk[2]
    c = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                b, o = block_address(i, j, k, sx, sy, sz, nby, nbz)
                s = ref[b]
                if s < 0:
                    for q in range(width):
                        out[c, q] = urow[b, q]
                else:
                    for q in range(width):
                        out[c, q] = pool[s, o, q]
                c += 1


@njit(cache=True, nogil=True)
def _expand_risk(shape, shift, nblk, ref, urisk, prisk, out):  # pragma: no cover - compiled
    nx, ny, nz = shape[0], shape[1], shape[2]
    sx, sy, sz = shift[0], shift[1], shift[2]
    nby, nbz = nblk[1], nblk[2]
    step = np.float32(RISK_STEP)
    c = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                b, o = block_address(i, j, k, sx, sy, sz, nby, nbz)
                s = ref[b]
                code = urisk[b] if s < 0 else prisk[s, o]
                out[c] = np.float32(code) * step
                c += 1


def _check_lut(lut: np.ndarray) -> np.ndarray:
    lut = np.ascontiguousarray(lut, dtype=np.int8)
    if lut.shape != (RISK_CODES,):
        raise ValueError(f"lut must have {RISK_CODES} entries (one a risk code), got shape {lut.shape}")
    return lut


@njit(cache=True, nogil=True)
def _lookup_flat(nx, ny, codes, bits, lut, unobserved, out):  # pragma: no cover - compiled
    for j in range(ny):
        for i in range(nx):
            c = i * ny + j
            out[j, i] = lut[codes[c]] if (bits[c >> 3] >> (c & 7)) & 1 else unobserved


@njit(cache=True, nogil=True)
def _lookup_blocks(shape, shift, nblk, ref, urisk, prisk, bits, lut, unobserved, out):  # pragma: no cover
    sx, sy, sz = shift[0], shift[1], shift[2]
    nby, nbz = nblk[1], nblk[2]
    for j in range(shape[1]):
        for i in range(shape[0]):
            b, o = block_address(i, j, 0, sx, sy, sz, nby, nbz)
            key = cell_id(b, o, sx, sy, sz)
            if (bits[key >> 3] >> (key & 7)) & 1:
                s = ref[b]
                out[j, i] = lut[urisk[b] if s < 0 else prisk[s, o]]
            else:
                out[j, i] = unobserved


@njit(cache=True, nogil=True)
def _expand_bits(shape, shift, nblk, bits, out):  # pragma: no cover - compiled
    nx, ny, nz = shape[0], shape[1], shape[2]
    sx, sy, sz = shift[0], shift[1], shift[2]
    nby, nbz = nblk[1], nblk[2]
    c = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                b, o = block_address(i, j, k, sx, sy, sz, nby, nbz)
                key = cell_id(b, o, sx, sy, sz)
                out[c] = (bits[key >> 3] >> (key & 7)) & 1
                c += 1
