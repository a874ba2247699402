"""The risk objective as native code inside OMPL: no C++ compiler, no Python call per edge.

Why: OMPL calls the objective's ``motionCost`` from C++ for every edge it weighs (RRTstar: about
20 per iteration). Overridden in Python, one call costs about 1 us, 0.6 us of which is the
crossing from C++ into Python itself, and RRTstar loses half its iterations to it
(``bench/README.md``). The OMPL wheel ships ``libompl.so`` but no headers, so a C++ subclass
cannot be compiled against it, and a fresh machine may have no C++ compiler anyway.

How: the objective is a plain ``PathLengthOptimizationObjective`` made through the bindings,
whose C++ object is pointed at a private copy of its class's virtual table in which

- the ``motionCost`` slot holds a numba ``cfunc`` with ``motionCost``'s C++ signature
  (``_native_kernels.py``), which reads the states' coordinates from OMPL's state structs and
  walks the packed grid with the same kernel as the Python objective of ``spaces.py``;
- the ``motionCostHeuristic`` slot holds the class's own ``motionCost``, the length, because
  the class's heuristic calls ``motionCost`` and would then overestimate;
- the word after the copied slots holds the packed grid's address.

Everything else (cost-to-go, informed sampler, combination of costs) stays the class's C++,
exactly as with the Python subclass. :meth:`NativeObjective.release` points the object back at
its class's table, so a table is reused only when no objective uses it.

Everything the trick assumes is verified once per process and state space before it is used,
reading only memory known to be mapped or through ``/proc/self/mem`` (which fails cleanly on a
bad address instead of crashing): x86-64 Linux; the library's exported symbols; nanobind
storing the object inline, with the class's vtable as its first word; ``motionCost`` and the
heuristic found once each in the table; state layouts read back equal to what the bindings
report; and the patched objective's costs equal to the Python objective's on random segments.
Any failure logs one warning, and the Python objectives of ``spaces.py`` are used instead.
"""

from __future__ import annotations

import ctypes
import logging
import math
import os
import platform
import struct
import sys
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import ompl
from ompl import base as ob

from planning.packed import PackedGrid

log = logging.getLogger(__name__)

SPACES = ("R2", "R3", "SE2", "Dubins")

_VTABLE = "_ZTVN4ompl4base31PathLengthOptimizationObjectiveE"
_MOTION_COST = "_ZNK4ompl4base31PathLengthOptimizationObjective10motionCostEPKNS0_5StateES4_"
_HEURISTIC = "_ZNK4ompl4base31PathLengthOptimizationObjective19motionCostHeuristicEPKNS0_5StateES4_"

# nanobind's instance header (struct nb_inst): PyObject_HEAD, then the int32 offset of the C++
# object and a bit field in which bit 2 ("direct") says the object is stored inline at that offset
_NB_HEADER = 16
_NB_DIRECT = 1 << 2
_CHECK_SEGMENTS = 256

_enabled = True
_lock = threading.Lock()
_verdicts: dict[str, str] = {}  # state space -> "" when usable, else why not
_library: _Library | None = None


def set_enabled(enabled: bool) -> None:
    """Use native objectives when they pass their checks (the default), or never."""
    global _enabled
    _enabled = bool(enabled)


def status() -> dict[str, str]:
    """Per state space checked so far: "native", or why the Python objective is used."""
    with _lock:
        return {name: why or "native" for name, why in _verdicts.items()}


def _peek(address: int, size: int) -> bytes | None:
    """``size`` bytes at ``address`` of this process, None where nothing is mapped."""
    try:
        fd = os.open("/proc/self/mem", os.O_RDONLY)
    except OSError:
        return None
    try:
        data = os.pread(fd, size, address)
    except (OSError, OverflowError, ValueError):
        return None
    finally:
        os.close(fd)
    return data if len(data) == size else None


def _peek_word(address: int) -> int | None:
    data = _peek(address, 8)
    return None if data is None else struct.unpack("<Q", data)[0]


def _instance(obj: Any) -> tuple[int, bool] | None:
    """(offset of the C++ object or of the pointer to it, stored inline?) of a nanobind instance."""
    size = type(obj).__basicsize__
    if size < _NB_HEADER + 16:
        return None
    offset, flags = struct.unpack("<iI", ctypes.string_at(id(obj) + _NB_HEADER, 8))
    if not _NB_HEADER + 8 <= offset <= size - 8:
        return None
    return offset, bool(flags & _NB_DIRECT)


@dataclass
class _Library:
    vtable: int  # address of the class's vtable (its offset-to-top word)
    original: np.ndarray  # the class's table: 2 header words, then COPIED_SLOTS slots
    cost_slot: int
    heuristic_slot: int
    functions: dict[str, int]  # state space -> address of its cfunc
    free: list[np.ndarray] = field(default_factory=list)
    tables: list[np.ndarray] = field(default_factory=list)  # every table made: never freed


def _load_library() -> _Library:
    """The class's vtable and the compiled cost functions; raises RuntimeError when unusable."""
    if sys.platform != "linux" or platform.machine() not in ("x86_64", "AMD64"):
        raise RuntimeError(f"needs x86-64 Linux (System V calls), this is {sys.platform} {platform.machine()}")
    path = os.path.join(os.path.dirname(ompl.__file__), "libompl.so")
    try:
        lib = ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)  # the copy the bindings loaded
        vtable, cost, heuristic = (ctypes.cast(getattr(lib, s), ctypes.c_void_p).value for s in
                                   (_VTABLE, _MOTION_COST, _HEURISTIC))  # fmt: skip
    except (OSError, AttributeError) as exc:
        raise RuntimeError(f"OMPL's library or its symbols were not found: {exc}") from exc
    from planning import _native_kernels as nk  # compiles (or loads) the cost functions

    words = _peek(vtable, 8 * (2 + nk.COPIED_SLOTS)) if vtable else None
    if words is None:
        raise RuntimeError("the objective's virtual table could not be read")
    original = np.frombuffer(words, dtype=np.int64).copy()
    slots = original[2:].view(np.uint64)
    found = [np.flatnonzero(slots == np.uint64(f)) for f in (cost, heuristic)]
    if any(len(f) != 1 for f in found):
        raise RuntimeError("motionCost or motionCostHeuristic not found once in the virtual table")
    functions = {name: int(nk.COST_FUNCTIONS[name].address) for name in SPACES}
    return _Library(vtable, original, int(found[0][0]), int(found[1][0]), functions)


def _state_layout_ok(space: str, si: ob.SpaceInformation) -> bool:
    """Coordinates read through the layout ``_native_kernels`` assumes equal the bindings'."""
    state = si.allocState()  # owned by its Python wrapper, which frees it
    where = _instance(state)
    if where is None or where[1]:
        return False
    pointer = _peek_word(id(state) + where[0])
    if space in ("R2", "R3"):
        n = 2 if space == "R2" else 3
        for i in range(n):
            state[i] = 0.125 + i
        expected = tuple(state[i] for i in range(n))
        values = _peek_word(pointer + 8) if pointer else None
        data = _peek(values, 8 * n) if values else None
        return data is not None and struct.unpack(f"<{n}d", data) == expected
    state.setXY(0.375, 1.625)
    state.setYaw(-0.875)
    components = _peek_word(pointer + 8) if pointer else None
    xy_state = _peek_word(components) if components else None
    yaw_state = _peek_word(components + 8) if components else None
    values = _peek_word(xy_state + 8) if xy_state else None
    xy = _peek(values, 16) if values else None
    yaw = _peek(yaw_state + 8, 8) if yaw_state else None
    return (
        xy is not None
        and yaw is not None
        and struct.unpack("<2d", xy) == (state.getX(), state.getY())
        and struct.unpack("<d", yaw)[0] == state.getYaw()
    )


class NativeObjective:
    """A ``PathLengthOptimizationObjective`` whose ``motionCost`` is the compiled risk cost.

    Hand ``objective`` to OMPL; call :meth:`release` once the planner and problem are done
    with it (the object then costs plain length again and its table is reused).
    """

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid, space: str, library: _Library) -> None:
        self.objective = ob.PathLengthOptimizationObjective(si)
        self.grid = grid  # keeps the packed buffer alive while the table points at it
        self._library = library
        where = _instance(self.objective)
        if where is None or not where[1]:
            raise RuntimeError("nanobind does not store the objective inline")
        self._this = id(self.objective) + where[0]
        vptr = ctypes.c_uint64.from_address(self._this)
        if vptr.value != library.vtable + 16:
            raise RuntimeError("the objective's first word is not its class's virtual table")
        with _lock:
            table = library.free.pop() if library.free else None
        if table is None:
            table = np.empty(len(library.original) + 1, dtype=np.int64)
            with _lock:
                library.tables.append(table)
        table[:-1] = library.original
        table[2 + library.cost_slot] = library.functions[space]
        table[2 + library.heuristic_slot] = library.original[2 + library.cost_slot]
        table[-1] = grid.address
        self._table: np.ndarray | None = table
        vptr.value = int(table.ctypes.data) + 16

    def release(self) -> None:
        """Give the object back its class's table (idempotent)."""
        table, self._table = self._table, None
        if table is None:
            return
        ctypes.c_uint64.from_address(self._this).value = self._library.vtable + 16
        table[-1] = 0
        with _lock:
            self._library.free.append(table)

    def __del__(self) -> None:
        self.release()


def _agrees(native: NativeObjective, reference: ob.OptimizationObjective, si: ob.SpaceInformation,
            grid: PackedGrid, space: str) -> bool:  # fmt: skip
    """Costs of random segments, native against the Python objective: bit-identical."""
    rng = np.random.default_rng(0)
    low = np.asarray(grid.origin, dtype=float)
    high = low + np.asarray(grid.shape, dtype=float) * grid.resolution
    a, b = si.allocState(), si.allocState()  # owned by their Python wrappers
    for _ in range(_CHECK_SEGMENTS):
        for s in (a, b):
            p = rng.uniform(low, high)
            if space in ("R2", "R3"):
                for i, v in enumerate(p):
                    s[i] = float(v)
            else:
                s.setXY(float(p[0]), float(p[1]))
                s.setYaw(float(rng.uniform(-math.pi, math.pi)))
        if native.objective.motionCost(a, b).value() != reference.motionCost(a, b).value():
            return False
    return True


def native_objective(
    si: ob.SpaceInformation, grid: PackedGrid, space: str, reference: ob.OptimizationObjective
) -> NativeObjective | None:
    """The compiled risk objective for ``space``, or None where it is off or failed its checks.

    ``reference`` is the Python objective it must agree with (checked on the first call per
    process and state space).
    """
    global _library
    if not _enabled or space not in SPACES:
        return None
    with _lock:
        verdict = _verdicts.get(space)
    if verdict:
        return None
    try:
        if _library is None:
            _library = _load_library()
        if verdict is None and not _state_layout_ok(space, si):
            raise RuntimeError(f"{space} states are not laid out as expected")
        native = NativeObjective(si, grid, space, _library)
        if verdict is None and not _agrees(native, reference, si, grid, space):
            native.release()
            raise RuntimeError(f"native {space} costs differ from the Python objective's")
    except RuntimeError as exc:
        with _lock:
            _verdicts[space] = str(exc)
        log.warning("native risk objective off for %s, using the Python one: %s", space, exc)
        return None
    with _lock:
        _verdicts[space] = ""
    return native
