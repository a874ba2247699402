"""Cell ids block by block, for a grid cut into blocks of ``2**shift[a]`` cells along each axis ``a``.

The id of cell ``(i, j, k)`` is ``block << (sx + sy + sz) | offset``: ``block`` the C-order
index of ``(i >> sx, j >> sy, k >> sz)`` among the blocks covering the grid, ``offset`` the
C-order index of ``(i & mx, j & my, k & mz)`` in its block (``m = 2**s - 1``). With every
shift 0 (blocks of one cell) the id is the flat id. :func:`fuzzyocc.raycast.cast_rays` hands
out cells so numbered and ``fuzzyocc.grid.BlockGrid`` stores them so; both take these inline
helpers, with the shifts and block counts as scalars so that a caller's loop hoists what does
not change in it.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True, inline="always")
def block_address(i: int, j: int, k: int, sx: int, sy: int, sz: int, nby: int, nbz: int) -> tuple[int, int]:
    """``(block, offset)`` of cell ``(i, j, k)``; ``nby``, ``nbz`` blocks along y and z."""
    block = ((i >> sx) * nby + (j >> sy)) * nbz + (k >> sz)
    offset = ((i & ((1 << sx) - 1)) << sy | (j & ((1 << sy) - 1))) << sz | (k & ((1 << sz) - 1))
    return block, offset


@njit(cache=True, nogil=True, inline="always")
def cell_id(block: int, offset: int, sx: int, sy: int, sz: int) -> int:
    """The id of the cell at ``offset`` in ``block``."""
    return block << (sx + sy + sz) | offset
