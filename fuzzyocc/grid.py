"""Dense cell storage and the risk cache both storages share.

:class:`CellGrid` keeps the whole state of a bounded 2-D or 3-D grid (Bayes log-odds), cells
addressed by flat id (C order over ``spec.shape``, see :mod:`fuzzyocc.keys`). Bytes per cell:
the state's (4 for float32 log-odds) is the map itself; besides it the grid keeps 1 bit
(observed) and 2 bytes (risk cache, whose all-ones value also marks a cell whose risk is
stale, so no dirty mask is needed). The fuzzy maps' block storage is
:class:`fuzzyocc.blockgrid.BlockGrid`.

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

from fuzzyocc.config import GridSpec

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

    def clear_observed(self, cells: np.ndarray) -> None:
        """Record that ``cells`` (flat ids) are never observed again."""
        observed = self.observed()
        observed[cells] = False
        self._observed = np.packbits(observed, bitorder="little")

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
