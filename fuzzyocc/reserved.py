"""Arrays that grow without a copy: address space reserved up front, memory committed only where it is written.

Growing a numpy array means a new array and a copy into fresh memory. A growing map's slab pool grows by half each time
it fills, so by the time it held N slabs it had written about 3N slabs into fresh pages, and a page's first write is
what costs: on the 2-core bench machine, 200 MB into fresh pages took 1.7-4.3 s against 0.06 s into pages already
held (the pool's growth took 8.9 s of the 16 s six Ouster frames fused in). A :class:`Reserved` array maps the
address space of many rows at once (``MAP_NORESERVE``: nothing is committed), so that growing is a longer view of the
same memory, and shrinking gives the pages past the new end back to the system.
"""

from __future__ import annotations

import math
import mmap

import numpy as np


class Reserved:
    """Rows of ``row_shape`` and ``dtype``, room for ``rows`` of them reserved; :meth:`view` is the first ``n``."""

    def __init__(self, dtype: np.dtype | type, row_shape: tuple[int, ...], rows: int) -> None:
        self.dtype = np.dtype(dtype)
        self.row_shape = tuple(int(n) for n in row_shape)
        self.rows = int(rows)
        self._row_bytes = self.dtype.itemsize * math.prod(self.row_shape)
        flags = mmap.MAP_PRIVATE | getattr(mmap, "MAP_ANONYMOUS", 0x20) | getattr(mmap, "MAP_NORESERVE", 0)
        self._map = mmap.mmap(-1, max(1, self.rows * self._row_bytes), flags=flags)
        self._bytes = np.frombuffer(self._map, dtype=np.uint8)

    def view(self, n: int) -> np.ndarray:
        """The first ``n`` rows (``n <= rows``), writable, sharing the memory of every other view."""
        if not 0 <= n <= self.rows:
            raise ValueError(f"a view of {n} rows; {self.rows} are reserved")
        return self._bytes[: n * self._row_bytes].view(self.dtype).reshape(n, *self.row_shape)

    def release_from(self, n: int) -> None:
        """Give the memory of rows ``n`` onwards back to the system (whole pages; they read as zeros after)."""
        start = -(-n * self._row_bytes // mmap.PAGESIZE) * mmap.PAGESIZE
        if start < len(self._map) and hasattr(mmap, "MADV_DONTNEED"):
            self._map.madvise(mmap.MADV_DONTNEED, start, len(self._map) - start)
