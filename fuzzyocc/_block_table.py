"""The directory of a block store: integer block coordinates to the slot a block is stored in.

An open-addressing hash table (linear probing, at most half full) over 32-bit coordinates
``(bx, by, bz)``, as Bonxai and Voxblox key their blocks; a 2-D map keeps ``bz = 0``. Keys and
slots live in plain arrays so the compiled kernels of :mod:`fuzzyocc.blockgrid` and
:mod:`fuzzyocc.raycast` find blocks without leaving compiled code. The hash is the spatial
hash of Teschner et al., "Optimized spatial hashing for collision detection of deformable
objects" (2003).

:func:`insert` never grows the table: its caller makes room first (``BlockIndex.reserve``), and a deletion
moves later entries of its probe run back (no tombstones), so lookups stay short however many blocks come and go.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: An empty entry of the table's ``slots``.
EMPTY = -1


def new_table(capacity: int) -> tuple[np.ndarray, np.ndarray]:
    """``(keys, slots)`` of an empty table of ``capacity`` entries (a power of two)."""
    if capacity < 2 or capacity & (capacity - 1):
        raise ValueError(f"capacity must be a power of two >= 2, got {capacity}")
    return np.zeros((capacity, 3), dtype=np.int32), np.full(capacity, EMPTY, dtype=np.int32)


@njit(cache=True, nogil=True, inline="always")
def _home(bx: int, by: int, bz: int, mask: int) -> int:
    return ((np.int64(bx) * 73856093) ^ (np.int64(by) * 19349663) ^ (np.int64(bz) * 83492791)) & mask


@njit(cache=True, nogil=True)
def find(keys, slots, bx, by, bz):  # pragma: no cover - compiled
    """The slot of block ``(bx, by, bz)``, or ``EMPTY``."""
    mask = slots.shape[0] - 1
    h = _home(bx, by, bz, mask)
    while True:
        s = slots[h]
        if s == EMPTY:
            return EMPTY
        if keys[h, 0] == bx and keys[h, 1] == by and keys[h, 2] == bz:
            return s
        h = (h + 1) & mask


@njit(cache=True, nogil=True)
def insert(keys, slots, bx, by, bz, slot):  # pragma: no cover - compiled
    """Enter block ``(bx, by, bz)`` (absent) at ``slot``; the table must have a free entry."""
    mask = slots.shape[0] - 1
    h = _home(bx, by, bz, mask)
    while slots[h] != EMPTY:
        h = (h + 1) & mask
    keys[h, 0] = bx
    keys[h, 1] = by
    keys[h, 2] = bz
    slots[h] = slot


@njit(cache=True, nogil=True)
def relink(keys, slots, bx, by, bz, slot):  # pragma: no cover - compiled
    """Point the present block ``(bx, by, bz)`` at ``slot`` (its storage moved)."""
    mask = slots.shape[0] - 1
    h = _home(bx, by, bz, mask)
    while not (keys[h, 0] == bx and keys[h, 1] == by and keys[h, 2] == bz and slots[h] != EMPTY):
        h = (h + 1) & mask
    slots[h] = slot


@njit(cache=True, nogil=True)
def remove(keys, slots, bx, by, bz):  # pragma: no cover - compiled
    """Take the present block ``(bx, by, bz)`` out, shifting its probe run back (no tombstones)."""
    mask = slots.shape[0] - 1
    h = _home(bx, by, bz, mask)
    while not (keys[h, 0] == bx and keys[h, 1] == by and keys[h, 2] == bz and slots[h] != EMPTY):
        h = (h + 1) & mask
    slots[h] = EMPTY
    j = h
    while True:
        j = (j + 1) & mask
        if slots[j] == EMPTY:
            return
        home = _home(keys[j, 0], keys[j, 1], keys[j, 2], mask)
        # entry j may move into the hole at h unless its home lies cyclically in (h, j]
        if (j > h and (home <= h or home > j)) or (j < h and (home <= h and home > j)):
            keys[h, 0] = keys[j, 0]
            keys[h, 1] = keys[j, 1]
            keys[h, 2] = keys[j, 2]
            slots[h] = slots[j]
            slots[j] = EMPTY
            h = j


@njit(cache=True, nogil=True)
def _drop_many(keys, slots, coords, n, drop):  # pragma: no cover - compiled
    """``BlockIndex.drop`` of each slot of ``drop`` in order: the new count and the moves (to, from, how many)."""
    to = np.empty(drop.shape[0], np.int64)
    from_ = np.empty(drop.shape[0], np.int64)
    moves = 0
    for q in range(drop.shape[0]):
        slot = drop[q]
        last = n - 1
        remove(keys, slots, coords[slot, 0], coords[slot, 1], coords[slot, 2])
        if slot != last:
            coords[slot, 0], coords[slot, 1], coords[slot, 2] = coords[last, 0], coords[last, 1], coords[last, 2]
            relink(keys, slots, coords[slot, 0], coords[slot, 1], coords[slot, 2], slot)
            to[moves], from_[moves] = slot, last
            moves += 1
        n = last
    return n, to, from_, moves


@njit(cache=True, nogil=True)
def rebuild(coords, n, capacity):  # pragma: no cover - compiled
    """A table of ``capacity`` entries holding blocks ``coords[:n]`` at slots ``0..n-1``."""
    keys = np.zeros((capacity, 3), np.int32)
    slots = np.full(capacity, EMPTY, np.int32)
    for s in range(n):
        insert(keys, slots, coords[s, 0], coords[s, 1], coords[s, 2], s)
    return keys, slots


class BlockIndex:
    """Blocks of a lattice by integer coordinates, each stored at a slot ``0..n-1`` (slots stay packed).

    ``coords[s]`` are the coordinates of the block at slot ``s``. Arrays grow by :meth:`reserve`.
    """

    def __init__(self, capacity: int = 64) -> None:
        self.n = 0
        #: blocks dropped so far: with ``n``, what tells whether the slots are still those of a moment before
        self.dropped = 0
        self.coords = np.zeros((capacity, 3), dtype=np.int32)
        self.keys, self.slots = new_table(_table_size(capacity))

    @property
    def capacity(self) -> int:
        """Blocks the arrays hold before they must grow."""
        return int(self.coords.shape[0])

    def reserve(self, blocks: int) -> None:
        """Room for ``blocks`` more blocks than held now (the table kept at most half full)."""
        need = self.n + int(blocks)
        if need <= self.capacity:
            return
        capacity = max(need, 2 * self.capacity)
        coords = np.zeros((capacity, 3), dtype=np.int32)
        coords[: self.n] = self.coords[: self.n]
        self.coords = coords
        self.keys, self.slots = rebuild(self.coords, self.n, _table_size(capacity))

    def find(self, coords: np.ndarray) -> np.ndarray:
        """Slots of blocks ``coords`` ((m, 3) int), ``-1`` for blocks not held."""
        coords = np.ascontiguousarray(coords, dtype=np.int64).reshape(-1, 3)
        return _find_many(self.keys, self.slots, coords)

    def drop(self, slot: int) -> int:
        """Forget the block at ``slot``; the last block moves into it. Returns the slot that moved (its
        old number), which the caller's per-slot arrays must move the same way."""
        last = self.n - 1
        c = self.coords[slot]
        remove(self.keys, self.slots, int(c[0]), int(c[1]), int(c[2]))
        if slot != last:
            self.coords[slot] = self.coords[last]
            m = self.coords[slot]
            relink(self.keys, self.slots, int(m[0]), int(m[1]), int(m[2]), slot)
        self.n = last
        self.dropped += 1
        return last

    def drop_many(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`drop` each of ``slots`` (distinct, highest first), in one compiled pass: the moves made, in order,
        as ``(to, from)`` slot arrays, which the caller's per-slot arrays must make the same way (a forgetting map
        drops a whole loop's 210,000 blocks when its robot jumps: 1.4 s one :meth:`drop` at a time)."""
        self.n, to, from_, moves = _drop_many(self.keys, self.slots, self.coords, self.n,
                                              np.ascontiguousarray(slots, dtype=np.int64))
        self.dropped += int(len(slots))
        return to[:moves], from_[:moves]

    def nbytes(self) -> int:
        """Bytes of the index: coordinates and table."""
        return int(self.coords.nbytes + self.keys.nbytes + self.slots.nbytes)


def _table_size(capacity: int) -> int:
    return 1 << max(4, (2 * capacity - 1).bit_length())


@njit(cache=True, nogil=True)
def _find_many(keys, slots, coords):  # pragma: no cover - compiled
    out = np.empty(coords.shape[0], np.int32)
    for n in range(coords.shape[0]):
        out[n] = find(keys, slots, coords[n, 0], coords[n, 1], coords[n, 2])
    return out
