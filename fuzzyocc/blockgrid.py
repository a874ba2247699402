"""Block storage of a fuzzy map: rows of uint8 by hashed power-of-two blocks, allocated when a ray first
reaches them; and the fuzzy fusion that writes into it.

Cells lie on a lattice: cell ``(i, j, k)`` covers ``[lower + i * res, lower + (i + 1) * res)`` along
each axis (``lower`` is the map's: a fixed map's box corner, or the frame's origin for a growing map).
Blocks are ``2**shift`` cells along each axis (4 x 4 x 4 in 3-D, 4 x 4 in 2-D, narrower along an
axis a fixed box is thinner than that) keyed by their integer coordinates ``(i >> sx, j >> sy, k >>
sz)`` in a :class:`fuzzyocc._block_table.BlockIndex`, which gives each block a slot. A block not in
the index holds the initial row (never observed) and costs nothing; a block whose cells all hold the
same row keeps it once (OctoMap's pruning, on a two-level layout as in Bonxai); any other block is a
dense slab of rows in a pool. A scan expands the uniform blocks it changes, fuses, and collapses
the blocks it changed that came out uniform; the pool stays packed (a freed slab takes the last one).

Cells are addressed by key ``slot << sum(shift) | offset`` (as :func:`fuzzyocc.raycast.cast_into`
numbers them) in :meth:`BlockGrid.fuse` and :meth:`BlockGrid.mark_observed`, and by lattice
coordinates everywhere else. A fixed map's box is ``[0, box)``: edge blocks reach past it, and
their cells outside it are never read (they only count when the block collapses if they are in it).

What a row means is the caller's: rows are compared byte for byte, and a cell's risk (cached as
uint16 per cell of a dense block, one per uniform block, see :mod:`fuzzyocc.grid`) depends on its
row alone, so storage never changes a state or a risk.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import njit

from fuzzyocc import parallel
from fuzzyocc._block_table import BlockIndex, find, insert, rebuild
from fuzzyocc._engine_kernels import SLOPED, evidence_class, fuse_row, fuzzify_into
from fuzzyocc.engine import Fuzzifier
from fuzzyocc.reserved import Reserved
from fuzzyocc.grid import _STALE, RISK_STEP, RiskFn, RowFusion, _check_lut, dequantize_risk, quantize_risk

#: Cells a block holds along each axis, as a power of two: 4 x 4 x 4 in 3-D, 4 x 4 in 2-D (a 2-D grid is
#: one layer thick). On the 2-D bench scene 4 x 4 fused as fast as 8 x 8, with the same state and a
#: third less resident.
BLOCK_SHIFT_3D = 2
BLOCK_SHIFT_2D = 2
#: Slabs of address space a pool reserves at once (a fixed map's box may need fewer): 1 M slabs of a 3-D default
#: engine's map is 0.8 GB of address space, none of it memory until written.
POOL_RESERVE_SLABS = 1 << 20
#: Box side used for an unbounded lattice in the kernels (cells): no block reaches past it.
_UNBOUNDED = np.int64(1) << 60


def block_shift_for(ndim: int, box: tuple[int, ...] | None) -> tuple[int, int, int]:
    """The block size of a map: :data:`BLOCK_SHIFT_3D` / ``_2D``, no wider than a fixed box along an axis."""
    s = BLOCK_SHIFT_3D if ndim == 3 else BLOCK_SHIFT_2D
    shape = (*(box if box is not None else (1 << 30,) * ndim), *((1,) * (3 - ndim)))
    shift = [min(s, (int(n) - 1).bit_length()) for n in shape]
    if ndim == 2:
        shift[2] = 0
    return shift[0], shift[1], shift[2]


class BlockGrid:
    """Per-cell rows of uint8 (fuzzy activations) stored by hashed uniform-or-dense blocks.

    Parameters
    ----------
    ndim : int
        2 or 3.
    initial_row : (L,) uint8
        The row of a cell no ray reached.
    risk_fn : callable
        ``(n, L) rows -> (n,) risk``.
    box : tuple of int, optional
        A fixed map's shape in cells (its cells are ``[0, box)``); None for an unbounded lattice.
    """

    def __init__(self, ndim: int, initial_row: np.ndarray, risk_fn: RiskFn, box: tuple[int, ...] | None) -> None:
        if ndim not in (2, 3):
            raise ValueError(f"ndim must be 2 or 3, got {ndim}")
        if box is not None and len(box) != ndim:
            raise ValueError(f"box must have {ndim} values, got {box}")
        self.ndim = ndim
        self.box = None if box is None else tuple(int(n) for n in box)
        self._risk_fn = risk_fn
        self.block_shift = block_shift_for(ndim, self.box)
        self._shift = np.asarray(self.block_shift, dtype=np.int64)
        self._bits = int(self._shift.sum())
        self._block_cells = 1 << self._bits
        self._box3 = np.full(3, _UNBOUNDED, dtype=np.int64)
        if self.box is not None:
            self._box3[:] = 1
            self._box3[:ndim] = self.box
        self._init_row = np.ascontiguousarray(initial_row, dtype=np.uint8).reshape(-1).copy()
        self._width = int(self._init_row.size)
        self._init_code = np.uint16(quantize_risk(risk_fn(self._init_row[None, :]))[0])
        self.index = BlockIndex()
        self._slots_ready = 0  # slots whose per-slot arrays are initialised (the cast adds blocks to the index)
        self._ref = np.empty(0, dtype=np.int32)  # pool slab of a dense block, -1 = uniform
        self._urow = np.empty((0, self._width), dtype=np.uint8)  # the row of a uniform block
        self._urisk = np.empty(0, dtype=np.uint16)
        self._obs = np.empty((0, max(1, self._block_cells // 8)), dtype=np.uint8)  # observed bits by slot
        self._n_dense = 0
        self._reserved: tuple[Reserved, Reserved, Reserved] | None = None
        self._alloc_pool(0)
        self._any_stale = False
        self.adopt()

    # -- slots ----------------------------------------------------------------------------
    def adopt(self) -> None:
        """Give the blocks the index gained since the last call (a cast adds them) their initial state."""
        cap = self.index.capacity
        if self._ref.shape[0] < cap:
            n = self._slots_ready
            ref = np.full(cap, -1, dtype=np.int32)
            urow = np.empty((cap, self._width), dtype=np.uint8)
            urisk = np.empty(cap, dtype=np.uint16)
            obs = np.zeros((cap, self._obs.shape[1]), dtype=np.uint8)
            ref[:n], urow[:n], urisk[:n], obs[:n] = self._ref[:n], self._urow[:n], self._urisk[:n], self._obs[:n]
            self._ref, self._urow, self._urisk, self._obs = ref, urow, urisk, obs
        first, last = self._slots_ready, self.index.n
        if last > first:
            self._ref[first:last] = -1
            self._urow[first:last] = self._init_row
            self._urisk[first:last] = self._init_code
            self._obs[first:last] = 0
        self._slots_ready = last

    @property
    def blocks(self) -> int:
        """Blocks held (reached by some ray and not freed since)."""
        return self.index.n

    def _alloc_pool(self, capacity: int) -> None:
        """Room for ``capacity`` slabs (at least the dense ones): views of the reserved pool, which is mapped anew,
        with a copy, only when ``capacity`` passes its reservation."""
        n = self._n_dense
        reserved = self._reserved
        if reserved is None or capacity > reserved[0].rows:
            rows = max(capacity, min(POOL_RESERVE_SLABS, self._most_blocks()))
            reserved = (Reserved(np.uint8, (self._block_cells, self._width), rows),
                        Reserved(np.uint16, (self._block_cells,), rows),
                        Reserved(np.int32, (), rows))  # the slot of each slab's block, to move a slab
            if n:
                for new, old in zip(reserved, (self._pool, self._prisk, self._owner)):
                    new.view(n)[:] = old[:n]
            self._reserved = reserved
        elif capacity < self._pool.shape[0]:
            for part in reserved:
                part.release_from(capacity)
        self._pool, self._prisk, self._owner = (part.view(capacity) for part in reserved)

    def __getstate__(self) -> dict[str, object]:
        # a copy or a pickle holds the pool's arrays as they are; it reserves address space of its own when its pool
        # next grows (a mapping is neither copied nor pickled)
        state = dict(self.__dict__)
        state["_reserved"] = None
        return state

    def _most_blocks(self) -> int:
        """The most blocks this grid can hold: its box's, or any number for a growing one."""
        if self.box is None:
            return POOL_RESERVE_SLABS
        return math.prod(((n - 1) >> s) + 1 for n, s in zip(self.box, self.block_shift))

    def _grow_pool(self, capacity: int) -> None:
        self._alloc_pool(max(capacity, self._n_dense))

    # -- building -------------------------------------------------------------------------
    @classmethod
    def from_dense(cls, box: tuple[int, ...], state: np.ndarray, observed: np.ndarray, initial_row: np.ndarray,
                   risk_fn: RiskFn) -> BlockGrid:
        """A fixed map's grid holding ``state`` ((num_cells, L) uint8, C order over ``box``) and ``observed``.

        Blocks whose in-box cells all hold the initial row and none of which is observed are not
        allocated."""
        n = int(np.prod(box))
        if state.ndim != 2 or state.shape[0] != n or state.dtype != np.uint8:
            raise ValueError(f"state must be uint8 of shape ({n}, L) (one row per cell)")
        if observed.shape != (n,) or observed.dtype != np.bool_:
            raise ValueError(f"observed must be bool of shape ({n},)")
        grid = cls(len(box), initial_row, risk_fn, box)
        shape = grid._box3
        state = np.ascontiguousarray(state)
        obs = np.ascontiguousarray(observed)
        nblk = (shape + (1 << grid._shift) - 1) >> grid._shift
        kind = _classify_blocks(state, obs, shape, grid._shift, nblk, grid._init_row)
        grid.index.reserve(int(np.count_nonzero(kind >= 0)))
        n_dense = int(np.count_nonzero(kind == 1))
        grid._grow_pool(n_dense)
        grid.index.n = _fill_blocks(state, obs, shape, grid._shift, nblk, kind, grid.index.keys, grid.index.slots,
                                    grid.index.coords)
        grid.adopt()
        grid._n_dense = _fill_slots(state, obs, shape, grid._shift, grid.index.coords, grid.index.n, grid._ref,
                                    grid._urow, grid._obs, grid._pool, grid._owner)
        grid._prisk[: grid._n_dense] = _STALE
        grid._urisk[: grid.index.n] = _STALE
        grid._any_stale = True
        return grid

    # -- fusion ---------------------------------------------------------------------------
    def fuse(self, cells: np.ndarray, distance_sigmas: np.ndarray, fuzzifier: Fuzzifier,
             row_fusion: RowFusion) -> None:
        """Fuse the evidence at ``distance_sigmas`` ((n,) float, no NaN; -inf: no evidence, skipped) into the rows of
        ``cells`` (keys, unique, a block's together).

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
        parts = _block_parts(keys, self._bits, parallel.walks_for(keys.size))
        if len(parts) > 2:
            touched = self._fuse_apart(keys, distance_sigmas, fuzzifier, rules, float_ops, parts)
        else:
            touched = np.empty(keys.size, dtype=np.int64)
            start = n_touched = 0
            while True:  # the pool grows only when a uniform block must be expanded and no slab is left
                start, self._n_dense, n_touched = _fuse_write(
                    keys, self._bits, distance_sigmas, *fuzzifier, rules, float_ops, start, keys.size, touched,
                    n_touched, self._ref, self._urow, self._urisk, self._pool.reshape(-1, self._width), self._prisk,
                    self._owner, self._n_dense, self._prisk.shape[0])
                if start == keys.size:
                    break
                self._grow_pool(self._n_dense + max(64, self._n_dense // 2))
            touched = touched[:n_touched]
        if touched.size == 0:
            return
        self._n_dense = _collapse(touched, self.index.coords, self._box3, self._shift, self._ref,
                                  self._urow, self._urisk, self._pool, self._prisk, self._owner, self._n_dense)
        self._give_back_slack()
        self._any_stale = True

    def _fuse_apart(self, keys: np.ndarray, distance_sigmas: np.ndarray, fuzzifier: Fuzzifier, rules: np.ndarray,
                    float_ops: np.ndarray, parts: np.ndarray) -> np.ndarray:
        """``fuse``'s writes in threads, each over its own blocks (``parts`` bounds runs of whole blocks); the blocks
        they touched, in key order.

        Each part takes its slabs from a range of the pool of its own, as many as it has uniform blocks (the most it
        can expand); the parts' slabs are then packed in part order: the slabs come out numbered as one pass over
        the keys numbers them, so the grid is the same, bit for bit, however the keys were split."""
        bounds = np.array([_uniform_blocks(keys, self._bits, self._ref, lo, hi) for lo, hi in zip(parts, parts[1:])])
        firsts = self._n_dense + np.concatenate([[0], np.cumsum(bounds)])
        if firsts[-1] > self._prisk.shape[0]:
            self._grow_pool(int(firsts[-1]))
        touched = np.empty(keys.size, dtype=np.int64)
        rows = self._pool.reshape(-1, self._width)

        def write(p: int) -> tuple[int, int]:
            lo, hi = int(parts[p]), int(parts[p + 1])
            _, dense, n_touched = _fuse_write(
                keys, self._bits, distance_sigmas, *fuzzifier, rules, float_ops, lo, hi, touched[lo:hi], 0,
                self._ref, self._urow, self._urisk, rows, self._prisk, self._owner, int(firsts[p]), int(firsts[p + 1]))
            return dense, n_touched

        done = parallel.run(write, range(len(parts) - 1))
        ends = np.array([dense for dense, _ in done], dtype=np.int64)
        self._n_dense = _pack_slabs(firsts[:-1].astype(np.int64), ends, self._ref, self._pool, self._prisk,
                                    self._owner)
        return np.concatenate([touched[lo: lo + n] for lo, (_, n) in zip(parts, done)])

    def _give_back_slack(self) -> None:
        if 2 * self._n_dense < self._pool.shape[0] and self._pool.shape[0] > 64:
            self._grow_pool(self._n_dense + self._n_dense // 4)

    def ids(self, cells: np.ndarray) -> np.ndarray:
        """The keys of ``cells`` (flat ids over a fixed box), as :meth:`fuse` and :meth:`mark_observed` take them;
        the blocks they lie in are held from now on (as a cast that reached them would)."""
        lattice = self._flat_to_cells(cells)
        blocks = lattice >> self._shift
        self.index.reserve(int(np.unique(blocks, axis=0).shape[0]) if blocks.size else 0)
        self.index.n, slots = _enter_blocks(blocks, self.index.keys, self.index.slots, self.index.coords, self.index.n)
        self.adopt()
        inner = lattice & ((1 << self._shift) - 1)
        offsets = (inner[:, 0] << self._shift[1] | inner[:, 1]) << self._shift[2] | inner[:, 2]
        return (slots.astype(np.int64) << self._bits) | offsets

    def mark_observed(self, cells: np.ndarray) -> None:
        """Record that beams reached ``cells`` (keys)."""
        _set_observed(self._obs, np.ascontiguousarray(cells, dtype=np.int64), self._bits)

    # -- clearing ---------------------------------------------------------------------------
    def clear_box(self, lo: np.ndarray, hi: np.ndarray) -> int:
        """Set the cells of ``[lo, hi)`` (lattice coordinates, (3,) ints; clipped to a fixed box) back to never
        observed; returns how many were observed. Blocks left holding nothing are freed."""
        lo, hi = self._clip(lo, hi)
        if np.any(hi <= lo):
            return 0
        count = self._resumable(lambda start: _clear_box(
            start, lo, hi, self.index.coords, self.index.n, self._shift, self._ref, self._urow, self._urisk, self._obs,
            self._pool, self._prisk, self._owner, self._n_dense, self._init_row, self._init_code, self._box3))
        self._free_empty()
        return count

    def forget_beyond(self, centre: np.ndarray, radius_cells: float) -> int:
        """Set every cell whose centre lies farther than ``radius_cells`` from ``centre`` (lattice units, (3,);
        only the first ``ndim`` axes count) back to never observed; returns how many were observed."""
        c = np.zeros(3)
        c[: self.ndim] = np.asarray(centre, dtype=np.float64)[: self.ndim]
        count = self._resumable(lambda start: _forget_beyond(
            start, c, float(radius_cells), self.ndim, self.index.coords, self.index.n, self._shift, self._ref,
            self._urow, self._urisk, self._obs, self._pool, self._prisk, self._owner, self._n_dense, self._init_row,
            self._init_code, self._box3))
        self._free_empty()
        return count

    def _resumable(self, step: Callable[[int], tuple[int, int, int]]) -> int:
        """Run a block-by-block reset from slot 0, growing the pool whenever it stops for want of a slab."""
        total, start = 0, 0
        while True:
            count, self._n_dense, start = step(start)
            total += int(count)
            if start == self.index.n:
                break
            self._grow_pool(self._n_dense + max(64, self._n_dense // 2))
        self._any_stale = True
        return total

    def _free_empty(self) -> None:
        """Drop the blocks that hold nothing (the initial row, uniform, nothing observed): they cost nothing again."""
        empty = _empty_slots(self._ref, self._urow, self._obs, self.index.n, self._init_row)
        if empty.size:
            # highest first: a moved block never lands on a slot still to drop
            to, from_ = self.index.drop_many(empty[::-1])
            _move_slots(to, from_, self._ref, self._urow, self._urisk, self._obs, self._owner)
        self._slots_ready = self.index.n
        self._give_back_slack()

    # -- reads ----------------------------------------------------------------------------
    def _clip(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo3 = np.zeros(3, dtype=np.int64)
        hi3 = np.ones(3, dtype=np.int64)
        lo3[: self.ndim] = np.asarray(lo, dtype=np.int64)[: self.ndim]
        hi3[: self.ndim] = np.asarray(hi, dtype=np.int64)[: self.ndim]
        if self.box is not None:
            lo3 = np.maximum(lo3, 0)
            hi3 = np.minimum(hi3, self._box3)
        return lo3, hi3

    def _box_slots(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slot of every block meeting ``[lo, hi)`` ((3,) ints), -1 where none; and the first block's coordinates."""
        blo = lo >> self._shift
        bhi = ((hi - 1) >> self._shift) + 1
        return _block_slots(blo, bhi, self.index.keys, self.index.slots), blo

    def _refresh(self) -> None:
        if not self._any_stale:
            return
        codes = self._prisk[: self._n_dense].reshape(-1)
        stale = np.flatnonzero(codes == _STALE)
        if stale.size:  # padding rows past a box's edge hold a real row too: harmless to refresh
            codes[stale] = quantize_risk(self._risk_fn(self._pool[: self._n_dense].reshape(-1, self._width)[stale]))
        n = self.index.n
        stale = np.flatnonzero((self._urisk[:n] == _STALE) & (self._ref[:n] < 0))
        if stale.size:
            self._urisk[stale] = quantize_risk(self._risk_fn(self._urow[stale]))
        self._any_stale = False

    def rows_in(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Every cell's row in ``[lo, hi)``, a new ``(cells, L)`` array in C order."""
        lo, hi = self._clip(lo, hi)
        out = np.empty((int(np.prod(np.maximum(hi - lo, 0))), self._width), dtype=np.uint8)
        if out.shape[0]:
            bslot, blo = self._box_slots(lo, hi)
            _expand_rows(lo, hi, self._shift, bslot, blo, self._ref, self._urow, self._pool, self._init_row, out)
        return out

    def risk_in(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Risk of every cell in ``[lo, hi)``, a new float32 array in C order."""
        return dequantize_risk(self.codes_in(lo, hi))

    def codes_in(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Cached risk codes of every cell in ``[lo, hi)``, a new uint16 array in C order."""
        self._refresh()
        lo, hi = self._clip(lo, hi)
        out = np.empty(int(np.prod(np.maximum(hi - lo, 0))), dtype=np.uint16)
        if out.size:
            bslot, blo = self._box_slots(lo, hi)
            _expand_codes(lo, hi, self._shift, bslot, blo, self._ref, self._urisk, self._prisk, self._init_code, out)
        return out

    def observed_in(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Whether some beam reached each cell in ``[lo, hi)``, a new bool array in C order."""
        lo, hi = self._clip(lo, hi)
        out = np.empty(int(np.prod(np.maximum(hi - lo, 0))), dtype=np.bool_)
        if out.size:
            bslot, blo = self._box_slots(lo, hi)
            _expand_observed(lo, hi, self._shift, bslot, blo, self._obs, out)
        return out

    def plane_lookup_in(self, lo: np.ndarray, hi: np.ndarray, lut: np.ndarray, unobserved: int) -> np.ndarray:
        """A 2-D grid's cells in ``[lo, hi)`` as (ny, nx) int8: ``lut[code]`` of each cell's risk code,
        ``unobserved`` where no beam reached; rows along y (an image's, or ``nav_msgs/OccupancyGrid``'s, order)."""
        self._refresh()
        lo, hi = self._clip(lo, hi)
        nx, ny = int(max(hi[0] - lo[0], 0)), int(max(hi[1] - lo[1], 0))
        out = np.empty((ny, nx), dtype=np.int8)
        if out.size:
            bslot, blo = self._box_slots(lo, hi)
            _lookup_plane(lo, hi, self._shift, bslot, blo, self._ref, self._urisk, self._prisk, self._obs,
                          _check_lut(lut), np.int8(unobserved), out)
        return out

    def _keys_of(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(slot, offset)`` of lattice cells ((m, 3) int64); slot -1 for cells of blocks not held."""
        cells = np.ascontiguousarray(cells, dtype=np.int64).reshape(-1, 3)
        blocks = cells >> self._shift
        slots = self.index.find(blocks)
        inner = cells & ((1 << self._shift) - 1)
        offsets = (inner[:, 0] << self._shift[1] | inner[:, 1]) << self._shift[2] | inner[:, 2]
        return slots, offsets

    def risk_at(self, cells: np.ndarray) -> np.ndarray:
        """(m,) float32 risk of lattice cells ((m, 3) ints; z 0 in 2-D), as :meth:`risk_in` gives it."""
        self._refresh()
        slots, offsets = self._keys_of(cells)
        return dequantize_risk(_gather_codes(slots, offsets, self._ref, self._urisk, self._prisk, self._init_code))

    def rows_at(self, cells: np.ndarray) -> np.ndarray:
        """Rows of lattice cells ((m, 3) ints), a new ``(m, L)`` array."""
        slots, offsets = self._keys_of(cells)
        return _gather_rows(slots, offsets, self._ref, self._urow, self._pool, self._init_row)

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(lo, hi)``: the smallest box ``[lo, hi)`` of lattice cells ((3,) ints) holding every observed cell;
        None while none is."""
        lo, hi, found = _observed_bounds(self.index.coords, self.index.n, self._shift, self._obs, self._box3)
        return (lo, hi) if found else None

    # -- a fixed box as a whole, cells by flat id (C order over the box) ------------------------
    def _whole(self) -> tuple[np.ndarray, np.ndarray]:
        if self.box is None:
            raise ValueError("a growing grid has no box: read a window of it")
        return np.zeros(3, dtype=np.int64), self._box3.copy()

    def _flat_to_cells(self, flat: np.ndarray) -> np.ndarray:
        _, hi = self._whole()
        return np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), tuple(int(v) for v in hi)), axis=1)

    def risk(self) -> np.ndarray:
        """(num_cells,) float32 risk of the whole box, a new array."""
        return self.risk_in(*self._whole())

    def observed(self) -> np.ndarray:
        """(num_cells,) bool: cells of the box some beam reached (a new array)."""
        return self.observed_in(*self._whole())

    def dense(self) -> np.ndarray:
        """Every cell's row, a new ``(num_cells, L)`` array in C order over the box."""
        return self.rows_in(*self._whole())

    def plane_lookup(self, lut: np.ndarray, unobserved: int) -> np.ndarray:
        """:meth:`plane_lookup_in` of the whole box."""
        return self.plane_lookup_in(*self._whole(), lut, unobserved)

    def risk_of(self, cells: np.ndarray) -> np.ndarray:
        """(len(cells),) float32 risk of ``cells`` (flat ids over the box), as :meth:`risk` gives it."""
        return self.risk_at(self._flat_to_cells(cells))

    def read(self, cells: np.ndarray) -> np.ndarray:
        """Rows of ``cells`` (flat ids over the box), a new ``(len(cells), L)`` array."""
        return self.rows_at(self._flat_to_cells(cells))

    # -- persistence ----------------------------------------------------------------------
    def to_blocks(self, copy: bool = True) -> dict[str, np.ndarray]:
        """The blocks held, as arrays (copies; views of the grid's own with ``copy=False``, for a caller that
        keeps every other thread off the grid while it reads them): what :meth:`from_blocks` restores bit for bit."""
        n, d = self.index.n, self._n_dense
        arrays = {
            "block_coords": self.index.coords[:n],
            "block_slab": self._ref[:n],
            "block_row": self._urow[:n],
            "block_observed": self._obs[:n],
            "slabs": self._pool[:d],
        }
        return {name: array.copy() for name, array in arrays.items()} if copy else arrays

    @classmethod
    def from_blocks(cls, ndim: int, arrays: dict[str, np.ndarray], initial_row: np.ndarray, risk_fn: RiskFn,
                    box: tuple[int, ...] | None = None) -> BlockGrid:
        """A grid holding the blocks of :meth:`to_blocks`; ``ValueError`` naming the array that does not fit."""
        grid = cls(ndim, initial_row, risk_fn, box)
        coords = _array(arrays, "block_coords", np.int32, (-1, 3))
        n = coords.shape[0]
        slab = _array(arrays, "block_slab", np.int32, (n,))
        rows = _array(arrays, "block_row", np.uint8, (n, grid._width))
        observed = _array(arrays, "block_observed", np.uint8, (n, grid._obs.shape[1]))
        slabs = _array(arrays, "slabs", np.uint8, (-1, grid._block_cells, grid._width))
        dense = np.sort(slab[slab >= 0])
        if not np.array_equal(dense, np.arange(slabs.shape[0])):
            raise ValueError("arrays['block_slab'] must number the slabs 0..n-1 once each (-1 for a uniform block)")
        if ndim == 2 and np.any(coords[:, 2] != 0):
            raise ValueError("arrays['block_coords'] of a 2-D grid must have z 0")
        grid.index.reserve(n)
        grid.index.coords[:n] = coords
        grid.index.n = n
        grid.index.keys, grid.index.slots = rebuild(grid.index.coords, n, grid.index.slots.shape[0])
        # a block held twice is found at its first slot only (a hash lookup a block: np.unique over the rows, a sort
        # holding the GIL, took 0.12 s of a 2 s rebuild's switch)
        if not np.array_equal(grid.index.find(coords), np.arange(n)):
            raise ValueError("arrays['block_coords'] must not hold a block twice")
        grid.adopt()
        grid._ref[:n], grid._urow[:n], grid._obs[:n] = slab, rows, observed
        grid._grow_pool(slabs.shape[0])
        grid._n_dense = slabs.shape[0]
        grid._pool[: grid._n_dense] = slabs
        grid._owner[slab[slab >= 0]] = np.flatnonzero(slab >= 0)
        grid._prisk[: grid._n_dense] = _STALE
        grid._urisk[:n] = _STALE
        grid._any_stale = True
        return grid

    # -- memory ---------------------------------------------------------------------------
    def held_cells(self) -> int:
        """Cells the grid holds in memory: every cell of a dense block, one per uniform block."""
        return int(self._n_dense * self._block_cells + (self.index.n - self._n_dense))

    def persistent_nbytes(self) -> int:
        """Bytes of what the map is: dense slabs in use, the rows and observed bits of the blocks held and
        their coordinates."""
        n = self.index.n
        slabs = self._n_dense * self._block_cells * self._width
        per_block = 4 + self._width + self._obs.shape[1] + 12  # ref, row, observed bits, coordinates
        return int(slabs + n * per_block)

    def resident_nbytes(self) -> int:
        """Bytes held between calls: the whole pool (spare slabs too), risk caches, per-block arrays, index."""
        arrays = (self._ref, self._urow, self._urisk, self._obs, self._pool, self._prisk, self._owner)
        return int(sum(a.nbytes for a in arrays) + self.index.nbytes())


def _array(arrays: dict[str, np.ndarray], key: str, dtype: type, shape: tuple[int, ...]) -> np.ndarray:
    if key not in arrays:
        raise ValueError(f"arrays lacks {key!r}")
    arr = np.asarray(arrays[key])
    if arr.dtype != dtype or arr.ndim != len(shape) or any(w not in (-1, g) for w, g in zip(shape, arr.shape)):
        raise ValueError(f"arrays[{key!r}] must be {np.dtype(dtype).name} of shape {shape} (-1: any), "
                         f"got {arr.dtype.name} of shape {arr.shape}")
    return np.ascontiguousarray(arr)


# ------------------------------------------------------------------ compiled kernels
@njit(cache=True, nogil=True)
def _set_observed(obs, cells, bits):  # pragma: no cover - compiled
    mask = (1 << bits) - 1
    for n in range(cells.shape[0]):
        c = cells[n]
        o = c & mask
        obs[c >> bits, o >> 3] |= np.uint8(1 << (o & 7))


@njit(cache=True, nogil=True, inline="always")
def _same_row(row, table, i):  # pragma: no cover - compiled
    """Whether ``row`` equals ``table[i]`` byte for byte."""
    for k in range(row.shape[0]):
        if row[k] != table[i, k]:
            return False
    return True


@njit(cache=True, nogil=True)
def _fuse_write(keys, bits, distances, xs, ys, counts, const_rows, bounds, rules, float_ops, start, stop, touched,
                n_touched, ref, urow, urisk, rows, prisk, owner, n_dense, capacity):  # pragma: no cover - compiled
    """Fuse cells ``start:stop``, writing the rows that change and expanding their uniform blocks into slabs
    ``n_dense:capacity``.

    ``rows`` is the pool as (slabs * block cells, L). Fused cells of dense blocks and changed
    cells of uniform ones are written, their risk goes stale and their blocks are appended
    to ``touched`` once each (a block's keys come together). A uniform block all of whose cells
    come with the same constant evidence is fused once, as a block, and stays uniform. Stops early,
    returning the cell to resume from, when a block needs a slab and the pool is full; nothing of
    that cell is written then. Returns ``(next cell, dense blocks, touched blocks)``.
    """
    width = urow.shape[1]
    mask = (1 << bits) - 1
    block_cells = prisk.shape[1]
    out = np.empty(width, np.uint8)
    acc = np.zeros(width)
    active = np.empty(width, np.int64)
    # The evidence rows: the engine's constant ones by class, and the sloped one, fuzzified here
    # (an (n, L) array of them cost more to write and read back than the fusion itself).
    evidence = np.empty((SLOPED + 1, width), np.uint8)
    for c in range(SLOPED):
        for k in range(width):
            evidence[c, k] = const_rows[c, k]
    # A uniform block's cells come one after another and most carry the same constant evidence
    # (free space far in front of the surface): once a row left the block's row unchanged, the
    # next cell of that block in the same class is skipped without fusing it again.
    noop_block = -1
    noop_class = -1
    n = start - 1
    while n + 1 < stop:
        n += 1
        v = distances[n]
        if v == -np.inf:  # reached only past the occupied region: pure unknown, which changes no row
            continue
        e = evidence_class(v, bounds)
        if e == SLOPED:
            fuzzify_into(v, xs, ys, counts, evidence, e)
        b = keys[n] >> bits
        o = keys[n] & mask
        s = ref[b]
        if s < 0:
            if b == noop_block and e == noop_class:
                continue
            if e != SLOPED and n + block_cells <= stop and keys[n + block_cells - 1] >> bits == b:
                # Every cell of the block is here (keys are unique, a block's together). If all take this
                # constant evidence the block stays uniform, with the fused row: it is neither expanded,
                # fused cell by cell, nor collapsed (in front of a robot whole blocks step from one free
                # level to the next together).
                whole = True
                for q in range(n + 1, n + block_cells):
                    if distances[q] == -np.inf or evidence_class(distances[q], bounds) != e:
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
    return stop, n_dense, n_touched


def _block_parts(keys: np.ndarray, bits: int, n: int) -> np.ndarray:
    """Bounds of ``n`` runs of ``keys`` (a block's together) of about equal length, each of whole blocks."""
    if n <= 1:
        return np.array([0, keys.size], dtype=np.int64)
    cuts = [0]
    for p in range(1, n):
        at = max(int(keys.size * p // n), cuts[-1])
        block = keys[at] >> bits if at < keys.size else None
        while at < keys.size and keys[at] >> bits == block:  # keys are sorted by block: no split inside one
            at += 1
        cuts.append(at)
    cuts.append(keys.size)
    return np.unique(np.array(cuts, dtype=np.int64))


@njit(cache=True, nogil=True)
def _uniform_blocks(keys, bits, ref, lo, hi):  # pragma: no cover - compiled
    """Uniform blocks among the cells ``keys[lo:hi]`` (a block's together): the most slabs their fusion can take."""
    n = 0
    last = -1
    for q in range(lo, hi):
        b = keys[q] >> bits
        if b != last:
            last = b
            if ref[b] < 0:
                n += 1
    return n


@njit(cache=True, nogil=True)
def _pack_slabs(firsts, ends, ref, pool, prisk, owner):  # pragma: no cover - compiled
    """Move the slabs parts took from ranges ``firsts[p]:ends[p]`` of the pool down, in part order, next to each other;
    the dense count."""
    n = ends[0]
    for p in range(1, firsts.shape[0]):
        for s in range(firsts[p], ends[p]):
            if s != n:
                _move_slab(s, n, ref, pool, prisk, owner)
            n += 1
    return n


@njit(cache=True, nogil=True, inline="always")
def _move_slab(s, to, ref, pool, prisk, owner):  # pragma: no cover - compiled
    """Slab ``s`` moves to ``to`` (its block's reference follows it)."""
    # element by element: a slice assignment would compile numba's shape-mismatch error
    # message formatting into this kernel (seconds more at the first start, on a cold cache)
    for o in range(pool.shape[1]):
        for k in range(pool.shape[2]):
            pool[to, o, k] = pool[s, o, k]
    for o in range(prisk.shape[1]):
        prisk[to, o] = prisk[s, o]
    b = owner[s]
    owner[to] = b
    ref[b] = to


@njit(cache=True, nogil=True, inline="always")
def _extent(coords, b, box, shift):  # pragma: no cover - compiled
    """Cells of block ``b`` inside the box along each axis (a fixed box cuts its edge blocks)."""
    ex = min(1 << shift[0], box[0] - (np.int64(coords[b, 0]) << shift[0]))
    ey = min(1 << shift[1], box[1] - (np.int64(coords[b, 1]) << shift[1]))
    ez = min(1 << shift[2], box[2] - (np.int64(coords[b, 2]) << shift[2]))
    return ex, ey, ez


@njit(cache=True, nogil=True)
def _slab_uniform(slab, ex, ey, ez, sy, sz):  # pragma: no cover - compiled
    """Whether the in-box rows of a dense slab are all equal (to its row 0, always in the box)."""
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
def _release_slab(b, s, ref, pool, prisk, owner, n_dense):  # pragma: no cover - compiled
    """Block ``b`` gives up slab ``s`` (it is uniform now): the last slab moves into the hole."""
    ref[b] = -1
    last = n_dense - 1
    if s != last:
        _move_slab(last, s, ref, pool, prisk, owner)
    return last


@njit(cache=True, nogil=True)
def _collapse(touched, coords, box, shift, ref, urow, urisk, pool, prisk, owner, n_dense):  # pragma: no cover
    """Collapse the ``touched`` blocks that became uniform; returns the dense count (pool kept packed)."""
    width = pool.shape[2]
    for t in range(touched.shape[0]):
        b = touched[t]
        s = ref[b]
        if s < 0:  # listed twice and collapsed already, or uniform all along
            continue
        ex, ey, ez = _extent(coords, b, box, shift)
        if not _slab_uniform(pool[s], ex, ey, ez, shift[1], shift[2]):
            continue
        for k in range(width):
            urow[b, k] = pool[s, 0, k]
        # All in-box cells hold one row, so any fresh code among them is the block's.
        code = _STALE
        for lx in range(ex):
            for ly in range(ey):
                base = (lx << shift[1] | ly) << shift[2]
                for lz in range(ez):
                    if prisk[s, base | lz] != _STALE:
                        code = prisk[s, base | lz]
        urisk[b] = code
        n_dense = _release_slab(b, s, ref, pool, prisk, owner, n_dense)
    return n_dense


@njit(cache=True, nogil=True)
def _classify_blocks(state, observed, shape, shift, nblk, init_row):  # pragma: no cover - compiled
    """Per block of a box (C order over ``nblk``): -1 nothing to hold, 0 uniform, 1 dense."""
    width = state.shape[1]
    ny, nz = shape[1], shape[2]
    kind = np.empty(nblk[0] * nblk[1] * nblk[2], np.int8)
    b = 0
    for bx in range(nblk[0]):
        for by in range(nblk[1]):
            for bz in range(nblk[2]):
                x0, y0, z0 = bx << shift[0], by << shift[1], bz << shift[2]
                first = (x0 * ny + y0) * nz + z0
                uniform = True
                seen = False
                for i in range(x0, min(x0 + (1 << shift[0]), shape[0])):
                    for j in range(y0, min(y0 + (1 << shift[1]), shape[1])):
                        for k in range(z0, min(z0 + (1 << shift[2]), shape[2])):
                            c = (i * ny + j) * nz + k
                            seen = seen or observed[c]
                            for q in range(width):
                                if state[c, q] != state[first, q]:
                                    uniform = False
                if not uniform:
                    kind[b] = 1
                elif seen:
                    kind[b] = 0
                else:
                    same = True
                    for q in range(width):
                        if state[first, q] != init_row[q]:
                            same = False
                    kind[b] = 0 if not same else -1
                b += 1
    return kind


@njit(cache=True, nogil=True)
def _fill_blocks(state, observed, shape, shift, nblk, kind, keys, slots, coords):  # pragma: no cover - compiled
    """Enter the blocks ``_classify_blocks`` keeps into the index (slots in C order); returns how many."""
    n = 0
    b = 0
    for bx in range(nblk[0]):
        for by in range(nblk[1]):
            for bz in range(nblk[2]):
                if kind[b] >= 0:
                    insert(keys, slots, bx, by, bz, n)
                    coords[n, 0] = bx
                    coords[n, 1] = by
                    coords[n, 2] = bz
                    n += 1
                b += 1
    return n


@njit(cache=True, nogil=True)
def _enter_blocks(blocks, keys, slots, coords, n):  # pragma: no cover - compiled
    """The slot of each block (added to the index if new; room reserved by the caller); returns ``(n, slots)``."""
    out = np.empty(blocks.shape[0], np.int32)
    for q in range(blocks.shape[0]):
        bx, by, bz = blocks[q, 0], blocks[q, 1], blocks[q, 2]
        s = find(keys, slots, bx, by, bz)
        if s < 0:
            s = n
            insert(keys, slots, bx, by, bz, s)
            coords[s, 0] = bx
            coords[s, 1] = by
            coords[s, 2] = bz
            n += 1
        out[q] = s
    return n, out


@njit(cache=True, nogil=True)
def _fill_slots(state, observed, shape, shift, coords, n, ref, urow, obs, pool, owner):  # pragma: no cover - compiled
    """Rows and observed bits of slots ``0..n-1`` from a box's dense state; returns how many blocks are dense."""
    width = state.shape[1]
    ny, nz = shape[1], shape[2]
    n_dense = 0
    for s in range(n):
        x0, y0, z0 = coords[s, 0] << shift[0], coords[s, 1] << shift[1], coords[s, 2] << shift[2]
        first = (x0 * ny + y0) * nz + z0
        uniform = True
        for i in range(x0, min(x0 + (1 << shift[0]), shape[0])):
            for j in range(y0, min(y0 + (1 << shift[1]), shape[1])):
                for k in range(z0, min(z0 + (1 << shift[2]), shape[2])):
                    c = (i * ny + j) * nz + k
                    o = ((i - x0) << shift[1] | (j - y0)) << shift[2] | (k - z0)
                    if observed[c]:
                        obs[s, o >> 3] |= np.uint8(1 << (o & 7))
                    for q in range(width):
                        if state[c, q] != state[first, q]:
                            uniform = False
        for q in range(width):
            urow[s, q] = state[first, q]
        if uniform:
            ref[s] = -1
            continue
        ref[s] = n_dense
        owner[n_dense] = s
        for o in range(pool.shape[1]):  # padding past the box: the block's first row
            for q in range(width):
                pool[n_dense, o, q] = state[first, q]
        for i in range(x0, min(x0 + (1 << shift[0]), shape[0])):
            for j in range(y0, min(y0 + (1 << shift[1]), shape[1])):
                for k in range(z0, min(z0 + (1 << shift[2]), shape[2])):
                    c = (i * ny + j) * nz + k
                    o = ((i - x0) << shift[1] | (j - y0)) << shift[2] | (k - z0)
                    for q in range(width):
                        pool[n_dense, o, q] = state[c, q]
        n_dense += 1
    return n_dense


@njit(cache=True, nogil=True)
def _block_slots(blo, bhi, keys, slots):  # pragma: no cover - compiled
    out = np.empty((bhi[0] - blo[0], bhi[1] - blo[1], bhi[2] - blo[2]), np.int32)
    for a in range(out.shape[0]):
        for b in range(out.shape[1]):
            for c in range(out.shape[2]):
                out[a, b, c] = find(keys, slots, blo[0] + a, blo[1] + b, blo[2] + c)
    return out


@njit(cache=True, nogil=True)
def _expand_rows(lo, hi, shift, bslot, blo, ref, urow, pool, init_row, out):  # pragma: no cover - compiled
    width = init_row.shape[0]
    mx, my, mz = (1 << shift[0]) - 1, (1 << shift[1]) - 1, (1 << shift[2]) - 1
    c = 0
    for i in range(lo[0], hi[0]):
        for j in range(lo[1], hi[1]):
            for k in range(lo[2], hi[2]):
                s = bslot[(i >> shift[0]) - blo[0], (j >> shift[1]) - blo[1], (k >> shift[2]) - blo[2]]
                if s < 0:
                    for q in range(width):
                        out[c, q] = init_row[q]
                elif ref[s] < 0:
                    for q in range(width):
                        out[c, q] = urow[s, q]
                else:
                    o = ((i & mx) << shift[1] | (j & my)) << shift[2] | (k & mz)
                    for q in range(width):
                        out[c, q] = pool[ref[s], o, q]
                c += 1


@njit(cache=True, nogil=True)
def _expand_codes(lo, hi, shift, bslot, blo, ref, urisk, prisk, init_code, out):  # pragma: no cover - compiled
    mx, my, mz = (1 << shift[0]) - 1, (1 << shift[1]) - 1, (1 << shift[2]) - 1
    c = 0
    for i in range(lo[0], hi[0]):
        for j in range(lo[1], hi[1]):
            for k in range(lo[2], hi[2]):
                s = bslot[(i >> shift[0]) - blo[0], (j >> shift[1]) - blo[1], (k >> shift[2]) - blo[2]]
                if s < 0:
                    out[c] = init_code
                elif ref[s] < 0:
                    out[c] = urisk[s]
                else:
                    out[c] = prisk[ref[s], ((i & mx) << shift[1] | (j & my)) << shift[2] | (k & mz)]
                c += 1


@njit(cache=True, nogil=True)
def _expand_observed(lo, hi, shift, bslot, blo, obs, out):  # pragma: no cover - compiled
    mx, my, mz = (1 << shift[0]) - 1, (1 << shift[1]) - 1, (1 << shift[2]) - 1
    c = 0
    for i in range(lo[0], hi[0]):
        for j in range(lo[1], hi[1]):
            for k in range(lo[2], hi[2]):
                s = bslot[(i >> shift[0]) - blo[0], (j >> shift[1]) - blo[1], (k >> shift[2]) - blo[2]]
                if s < 0:
                    out[c] = False
                else:
                    o = ((i & mx) << shift[1] | (j & my)) << shift[2] | (k & mz)
                    out[c] = (obs[s, o >> 3] >> (o & 7)) & 1
                c += 1


@njit(cache=True, nogil=True)
def _lookup_plane(lo, hi, shift, bslot, blo, ref, urisk, prisk, obs, lut, unobserved, out):  # pragma: no cover
    mx, my = (1 << shift[0]) - 1, (1 << shift[1]) - 1
    for j in range(lo[1], hi[1]):
        for i in range(lo[0], hi[0]):
            s = bslot[(i >> shift[0]) - blo[0], (j >> shift[1]) - blo[1], 0]
            v = unobserved
            if s >= 0:
                o = (i & mx) << shift[1] | (j & my)
                if (obs[s, o >> 3] >> (o & 7)) & 1:
                    v = lut[urisk[s] if ref[s] < 0 else prisk[ref[s], o]]
            out[j - lo[1], i - lo[0]] = v


@njit(cache=True, nogil=True)
def _gather_codes(slots, offsets, ref, urisk, prisk, init_code):  # pragma: no cover - compiled
    out = np.empty(slots.shape[0], np.uint16)
    for n in range(slots.shape[0]):
        s = slots[n]
        if s < 0:
            out[n] = init_code
        elif ref[s] < 0:
            out[n] = urisk[s]
        else:
            out[n] = prisk[ref[s], offsets[n]]
    return out


@njit(cache=True, nogil=True)
def _gather_rows(slots, offsets, ref, urow, pool, init_row):  # pragma: no cover - compiled
    width = init_row.shape[0]
    out = np.empty((slots.shape[0], width), np.uint8)
    for n in range(slots.shape[0]):
        s = slots[n]
        for q in range(width):
            if s < 0:
                out[n, q] = init_row[q]
            elif ref[s] < 0:
                out[n, q] = urow[s, q]
            else:
                out[n, q] = pool[ref[s], offsets[n], q]
    return out


@njit(cache=True, nogil=True)
def _observed_bounds(coords, n, shift, obs, box):  # pragma: no cover - compiled
    lo = np.full(3, np.int64(1) << 62)
    hi = np.full(3, -(np.int64(1) << 62))
    found = False
    for s in range(n):
        any_bit = False
        for q in range(obs.shape[1]):
            if obs[s, q] != 0:
                any_bit = True
                break
        if not any_bit:
            continue
        x0, y0, z0 = np.int64(coords[s, 0]) << shift[0], np.int64(coords[s, 1]) << shift[1], np.int64(coords[s, 2]) << shift[2]
        # Only a block that could widen the bounds is read bit by bit.
        if (x0 >= lo[0] and x0 + (1 << shift[0]) <= hi[0] and y0 >= lo[1] and y0 + (1 << shift[1]) <= hi[1]
                and z0 >= lo[2] and z0 + (1 << shift[2]) <= hi[2]):
            continue
        for lx in range(1 << shift[0]):
            for ly in range(1 << shift[1]):
                for lz in range(1 << shift[2]):
                    o = (lx << shift[1] | ly) << shift[2] | lz
                    if (obs[s, o >> 3] >> (o & 7)) & 1:
                        found = True
                        lo[0] = min(lo[0], x0 + lx)
                        lo[1] = min(lo[1], y0 + ly)
                        lo[2] = min(lo[2], z0 + lz)
                        hi[0] = max(hi[0], x0 + lx + 1)
                        hi[1] = max(hi[1], y0 + ly + 1)
                        hi[2] = max(hi[2], z0 + lz + 1)
    return lo, hi, found


@njit(cache=True, nogil=True)
def _reset_cell(s, o, ref, pool, prisk, obs, init_row, init_code):  # pragma: no cover - compiled
    """Cell ``o`` of the dense block at slot ``s`` back to the initial row, unobserved; whether it was observed."""
    was = (obs[s, o >> 3] >> (o & 7)) & 1
    obs[s, o >> 3] &= np.uint8(~(1 << (o & 7)) & 0xFF)
    for q in range(init_row.shape[0]):
        pool[ref[s], o, q] = init_row[q]
    prisk[ref[s], o] = init_code
    return was


@njit(cache=True, nogil=True)
def _expand_block(s, ref, urow, urisk, pool, prisk, owner, n_dense):  # pragma: no cover - compiled
    """Give the uniform block at slot ``s`` a slab holding its row (the pool has room); returns the dense count."""
    d = n_dense
    ref[s] = d
    owner[d] = s
    for o in range(pool.shape[1]):
        for q in range(urow.shape[1]):
            pool[d, o, q] = urow[s, q]
        prisk[d, o] = urisk[s]
    return n_dense + 1


@njit(cache=True, nogil=True)
def _count_bits(obs, s):  # pragma: no cover - compiled
    total = 0
    for q in range(obs.shape[1]):
        v = obs[s, q]
        while v:
            total += v & 1
            v >>= 1
    return total


@njit(cache=True, nogil=True)
def _reset_block(s, ref, urow, urisk, obs, pool, prisk, owner, n_dense, init_row, init_code):  # pragma: no cover
    """The whole block at slot ``s`` back to never observed; returns ``(observed cells it had, dense count)``."""
    was = _count_bits(obs, s)
    for q in range(obs.shape[1]):
        obs[s, q] = 0
    if ref[s] >= 0:
        n_dense = _release_slab(s, ref[s], ref, pool, prisk, owner, n_dense)
    for q in range(init_row.shape[0]):
        urow[s, q] = init_row[q]
    urisk[s] = init_code
    return was, n_dense


@njit(cache=True, nogil=True)
def _settle(s, coords, box, shift, ref, urow, urisk, pool, prisk, owner, n_dense):  # pragma: no cover - compiled
    """Collapse the block at slot ``s`` if it came out uniform; returns the dense count."""
    touched = np.empty(1, np.int64)
    touched[0] = s
    return _collapse(touched, coords, box, shift, ref, urow, urisk, pool, prisk, owner, n_dense)


@njit(cache=True, nogil=True)
def _clear_box(start, lo, hi, coords, n, shift, ref, urow, urisk, obs, pool, prisk, owner, n_dense, init_row, init_code,
               box):  # pragma: no cover - compiled
    count = 0
    side = np.empty(3, np.int64)
    for a in range(3):
        side[a] = 1 << shift[a]
    for s in range(start, n):
        x0, y0, z0 = np.int64(coords[s, 0]) << shift[0], np.int64(coords[s, 1]) << shift[1], np.int64(coords[s, 2]) << shift[2]
        ax0, ay0, az0 = max(x0, lo[0]), max(y0, lo[1]), max(z0, lo[2])
        ax1, ay1, az1 = min(x0 + side[0], hi[0]), min(y0 + side[1], hi[1]), min(z0 + side[2], hi[2])
        if ax0 >= ax1 or ay0 >= ay1 or az0 >= az1:
            continue
        ex, ey, ez = _extent(coords, s, box, shift)
        if ax0 <= x0 and ay0 <= y0 and az0 <= z0 and ax1 >= x0 + ex and ay1 >= y0 + ey and az1 >= z0 + ez:
            was, n_dense = _reset_block(s, ref, urow, urisk, obs, pool, prisk, owner, n_dense, init_row, init_code)
            count += was
            continue
        if ref[s] < 0:
            if n_dense == pool.shape[0]:
                return count, n_dense, s  # no slab left: the caller grows the pool and goes on from here
            n_dense = _expand_block(s, ref, urow, urisk, pool, prisk, owner, n_dense)
        for i in range(ax0, ax1):
            for j in range(ay0, ay1):
                for k in range(az0, az1):
                    o = ((i - x0) << shift[1] | (j - y0)) << shift[2] | (k - z0)
                    count += _reset_cell(s, o, ref, pool, prisk, obs, init_row, init_code)
        n_dense = _settle(s, coords, box, shift, ref, urow, urisk, pool, prisk, owner, n_dense)
    return count, n_dense, n


@njit(cache=True, nogil=True)
def _forget_beyond(start, c, radius, ndim, coords, n, shift, ref, urow, urisk, obs, pool, prisk, owner, n_dense, init_row,
                   init_code, box):  # pragma: no cover - compiled
    """Cells whose centre (lattice units: cell i's centre is i + 0.5) lies farther than ``radius`` from ``c``."""
    count = 0
    r2 = radius * radius
    for s in range(start, n):
        lo = np.empty(3)
        hi = np.empty(3)
        lo[0], lo[1], lo[2] = coords[s, 0] << shift[0], coords[s, 1] << shift[1], coords[s, 2] << shift[2]
        for a in range(3):
            hi[a] = lo[a] + (1 << shift[a])
        # nearest and farthest cell centres of the block
        near = 0.0
        far = 0.0
        for a in range(ndim):
            first, last = lo[a] + 0.5, hi[a] - 0.5
            d_near = max(first - c[a], 0.0, c[a] - last)
            d_far = max(abs(first - c[a]), abs(last - c[a]))
            near += d_near * d_near
            far += d_far * d_far
        if far <= r2:
            continue  # every cell within reach
        if near > r2:
            was, n_dense = _reset_block(s, ref, urow, urisk, obs, pool, prisk, owner, n_dense, init_row, init_code)
            count += was
            continue
        if ref[s] < 0:
            if n_dense == pool.shape[0]:
                return count, n_dense, s
            n_dense = _expand_block(s, ref, urow, urisk, pool, prisk, owner, n_dense)
        for lx in range(1 << shift[0]):
            for ly in range(1 << shift[1]):
                for lz in range(1 << shift[2]):
                    d2 = 0.0
                    cell = (lo[0] + lx + 0.5, lo[1] + ly + 0.5, lo[2] + lz + 0.5)
                    for a in range(ndim):
                        d2 += (cell[a] - c[a]) ** 2
                    if d2 > r2:
                        o = (lx << shift[1] | ly) << shift[2] | lz
                        count += _reset_cell(s, o, ref, pool, prisk, obs, init_row, init_code)
        n_dense = _settle(s, coords, box, shift, ref, urow, urisk, pool, prisk, owner, n_dense)
    return count, n_dense, n


@njit(cache=True, nogil=True)
def _move_slots(to, from_, ref, urow, urisk, obs, owner):  # pragma: no cover - compiled
    """The per-slot arrays moved as ``BlockIndex.drop_many`` moved the blocks, in its order."""
    for q in range(to.shape[0]):
        slot, moved = to[q], from_[q]
        ref[slot] = ref[moved]
        urow[slot] = urow[moved]
        urisk[slot] = urisk[moved]
        obs[slot] = obs[moved]
        if ref[slot] >= 0:
            owner[ref[slot]] = slot


@njit(cache=True, nogil=True)
def _empty_slots(ref, urow, obs, n, init_row):  # pragma: no cover - compiled
    out = np.empty(n, np.int64)
    m = 0
    for s in range(n):
        if ref[s] >= 0:
            continue
        empty = True
        for q in range(obs.shape[1]):
            if obs[s, q] != 0:
                empty = False
                break
        if empty:
            for q in range(init_row.shape[0]):
                if urow[s, q] != init_row[q]:
                    empty = False
                    break
        if empty:
            out[m] = s
            m += 1
    return out[:m]


__all__ = ["BLOCK_SHIFT_2D", "BLOCK_SHIFT_3D", "BlockGrid", "RISK_STEP", "block_shift_for"]
