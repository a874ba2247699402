"""Validity, motion checks and the risk objective as native code inside OMPL, no C++ compiler.

Why: OMPL calls these from C++ for every state and edge it weighs: RRTstar about 20
``motionCost`` calls per iteration, RRTConnect about 30 000 motion and 15 000 state checks per
plan on a maze. Overridden in Python, one call costs about 1 us, 0.6 us of which is the crossing
from C++ into Python itself (``bench/README.md``). The OMPL wheel ships ``libompl.so`` but no
headers, so a C++ subclass cannot be compiled against it, and a fresh machine may have no C++
compiler anyway.

How: a plain OMPL object (a ``PathLengthOptimizationObjective``, an
``AllValidStateValidityChecker``, or the ``DiscreteMotionValidator`` / ``DubinsMotionValidator``
that ``SpaceInformation.setup`` makes) is pointed at a private copy of its class's virtual
table in which the slots of ``motionCost`` / ``isValid`` / both ``checkMotion`` hold numba
``cfunc`` s with the same C++ signatures (``_native_kernels.py``). They read the states'
coordinates from OMPL's state structs and run the very kernels the Python callbacks of
``spaces.py`` run; the word after the copied slots holds the packed grid's address. The
objective's ``motionCostHeuristic`` slot gets the class's own ``motionCost`` (the length),
because the class's heuristic calls ``motionCost`` and would overestimate. Everything else
(cost-to-go, informed sampler, combination of costs) stays the class's C++.
:meth:`NativePatch.release` points the object back at its class's table, which is then reused.

Everything the trick assumes is verified once per process, kind and state space before it is
used, reading memory through ``/proc/self/mem`` (which fails cleanly on a bad address instead of
crashing) where it is not known to be mapped: x86-64 Linux; the library's exported symbols;
nanobind's instance layout; the object's class, by the name in its table's type info; each
function found once in its class's table; state layouts read back equal to what the bindings
report; and answers equal to the Python callbacks' on random states and segments. Any failure
logs one warning and the Python callbacks are used instead.
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
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import ompl
from ompl import base as ob

from planning.packed import PackedGrid

log = logging.getLogger(__name__)

SPACES = ("R2", "R3", "SE2", "Dubins")
KINDS = ("objective", "validity", "motion")

# The classes whose objects get private tables, by the mangled name in their type info: per
# role, the mangled name of the class's own function, looked up in the library and found in
# the class's table to locate the role's slot; and the class's vtable symbol, when the objects
# are made from Python (nanobind's module may hold its own copy of an inline class's table, whose
# functions are not exported: the slots are then located in the library's copy)
_DUBINS_MV = "N4ompl4base21DubinsMotionValidatorINS0_16DubinsStateSpaceEEE"
_CLASSES: dict[str, tuple[str | None, dict[str, str]]] = {
    "N4ompl4base31PathLengthOptimizationObjectiveE": (
        "_ZTVN4ompl4base31PathLengthOptimizationObjectiveE",
        {
            "cost": "_ZNK4ompl4base31PathLengthOptimizationObjective10motionCostEPKNS0_5StateES4_",
            "heuristic": "_ZNK4ompl4base31PathLengthOptimizationObjective19motionCostHeuristicEPKNS0_5StateES4_",
        },
    ),
    "N4ompl4base28AllValidStateValidityCheckerE": (
        "_ZTVN4ompl4base28AllValidStateValidityCheckerE",
        {"valid": "_ZNK4ompl4base28AllValidStateValidityChecker7isValidEPKNS0_5StateE"},
    ),
    "N4ompl4base23DiscreteMotionValidatorE": (
        None,
        {
            "check": "_ZNK4ompl4base23DiscreteMotionValidator11checkMotionEPKNS0_5StateES4_",
            "check_last": "_ZNK4ompl4base23DiscreteMotionValidator11checkMotionEPKNS0_5StateES4_RSt4pairIPS2_dE",
        },
    ),
    _DUBINS_MV: (
        None,
        {
            "check": "_ZNK4ompl4base21DubinsMotionValidatorINS0_16DubinsStateSpaceEE11checkMotionEPKNS0_5StateES6_",
            "check_last": "_ZNK4ompl4base21DubinsMotionValidatorINS0_16DubinsStateSpaceEE11checkMotionEPKNS0_5St"
            "ateES6_RSt4pairIPS4_dE",
        },
    ),
}

# nanobind's instance header (struct nb_inst): PyObject_HEAD, then the int32 offset of the C++
# object and a bit field in which bit 2 ("direct") says the object is stored inline at that offset
_NB_HEADER = 16
_NB_DIRECT = 1 << 2
_CHECKS = 256

_enabled = set(KINDS)
_lock = threading.Lock()
_verdicts: dict[str, str] = {}  # "role space" -> "" when usable, else why not
_library: ctypes.CDLL | None = None
_classes: dict[int, _Class] = {}  # by vtable address (each copy of a class's table apart)


def set_enabled(enabled: bool, kinds: Iterable[str] = KINDS) -> None:
    """Use the compiled ``kinds`` (of KINDS) where they pass their checks (the default), or never."""
    for kind in kinds:
        if kind not in KINDS:
            raise ValueError(f"unknown kind {kind!r}: one of {', '.join(KINDS)}")
        (_enabled.add if enabled else _enabled.discard)(kind)


def status() -> dict[str, str]:
    """Per "kind space" checked so far (e.g. "objective R2"): "native", or why Python is used."""
    with _lock:
        return {key: why or "native" for key, why in _verdicts.items()}


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


def _cpp_address(obj: Any, inline: bool) -> int | None:
    """Address of the C++ object behind a nanobind instance, stored inline or held by pointer."""
    where = _instance(obj)
    if where is None or where[1] != inline:
        return None
    return id(obj) + where[0] if inline else _peek_word(id(obj) + where[0])


@dataclass
class _Class:
    """One copy of a class's table: its words, its slots by role, and the private tables made from it."""

    vtable: int  # the address objects of this copy point at (its first slot)
    original: np.ndarray  # 2 header words (offset to top, type info), then COPIED_SLOTS slots
    slots: dict[str, int]  # role -> slot index
    free: list[np.ndarray] = field(default_factory=list)
    tables: list[np.ndarray] = field(default_factory=list)  # every table made: never freed


def _open_library() -> ctypes.CDLL:
    if sys.platform != "linux" or platform.machine() not in ("x86_64", "AMD64"):
        raise RuntimeError(f"needs x86-64 Linux (System V calls), this is {sys.platform} {platform.machine()}")
    path = os.path.join(os.path.dirname(ompl.__file__), "libompl.so")
    try:
        return ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)  # the copy the bindings loaded
    except OSError as exc:
        raise RuntimeError(f"OMPL's library was not found: {exc}") from exc


def _symbol(name: str) -> int:
    global _library
    if _library is None:
        _library = _open_library()
    try:
        return int(ctypes.cast(getattr(_library, name), ctypes.c_void_p).value or 0)
    except AttributeError as exc:
        raise RuntimeError(f"OMPL's library does not export {name}") from exc


def _table_words(vptr: int) -> np.ndarray:
    from planning._native_kernels import COPIED_SLOTS

    words = _peek(vptr - 16, 8 * (2 + COPIED_SLOTS))
    if words is None:
        raise RuntimeError("a virtual table could not be read")
    return np.frombuffer(words, dtype=np.int64).copy()


def _class_of(this: int) -> _Class:
    """The class of the C++ object at ``this``, identified by its type info, with its slots."""
    vptr = _peek_word(this)
    if vptr is None:
        raise RuntimeError("the object could not be read")
    with _lock:
        known = _classes.get(vptr)
        ours = any(vptr == int(t.ctypes.data) + 16 for c in _classes.values() for t in c.tables)
    if ours:
        raise RuntimeError("the object is already compiled")
    if known is not None:
        return known
    original = _table_words(vptr)
    info = int(original[1])
    name_at = _peek_word(info + 8) if info else None
    raw = _peek(name_at, 128) if name_at else None
    name = raw.split(b"\0", 1)[0].decode("ascii", "replace") if raw else ""
    if name not in _CLASSES:
        raise RuntimeError(f"unexpected class {name or '(unreadable)'}")
    vtable_symbol, roles = _CLASSES[name]
    reference = original if vtable_symbol is None else _table_words(_symbol(vtable_symbol) + 16)
    slots = {}
    for role, function in roles.items():
        found = np.flatnonzero(reference[2:].view(np.uint64) == np.uint64(_symbol(function)))
        if len(found) != 1:
            raise RuntimeError(f"{function} is not found once in its class's virtual table")
        slots[role] = int(found[0])
    cls = _Class(vptr, original, slots)
    with _lock:
        return _classes.setdefault(vptr, cls)


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


class NativePatch:
    """An OMPL object pointed at a private copy of its class's table, with compiled slots.

    ``functions`` maps roles of the class (see ``_CLASSES``) to a compiled function's address,
    or to the name of another role whose original function the slot should take. Holds the
    object (so it outlives the patch) and the packed grid its functions read. Call
    :meth:`release` once OMPL is done with it: the object gets its class's table back (and
    behaves as that class again) and the table is reused.
    """

    def __init__(self, obj: Any, this: int, grid: PackedGrid, functions: dict[str, int | str]) -> None:
        self._table: np.ndarray | None = None
        self.obj = obj
        self.grid = grid
        self._this = this
        self._cls = cls = _class_of(this)
        with _lock:
            table = cls.free.pop() if cls.free else None
            if table is None:
                table = np.empty(len(cls.original) + 1, dtype=np.int64)
                cls.tables.append(table)
        table[:-1] = cls.original
        for role, function in functions.items():
            slot = 2 + cls.slots[role]
            table[slot] = cls.original[2 + cls.slots[function]] if isinstance(function, str) else function
        table[-1] = grid.address
        self._table = table
        ctypes.c_uint64.from_address(this).value = int(table.ctypes.data) + 16

    def release(self) -> None:
        """Give the object back its class's table (idempotent)."""
        table, self._table = self._table, None
        if table is None:
            return
        ctypes.c_uint64.from_address(self._this).value = self._cls.vtable
        table[-1] = 0
        with _lock:
            self._cls.free.append(table)

    def __del__(self) -> None:
        self.release()


def _random_states(si: ob.SpaceInformation, grid: PackedGrid, space: str, n: int, margin: float) -> list[Any]:
    """``n`` states spread over the map, ``margin`` of its size beyond its edges (numpy's RNG:
    OMPL's global one is left alone, for seeded plans)."""
    rng = np.random.default_rng(0)
    low = np.asarray(grid.origin, dtype=float)
    size = np.asarray(grid.shape, dtype=float) * grid.resolution
    states = []
    for _ in range(n):
        p = rng.uniform(low - margin * size, low + (1.0 + margin) * size)
        s = si.allocState()  # owned by its Python wrapper
        if space in ("R2", "R3"):
            for i, v in enumerate(p):
                s[i] = float(v)
        else:
            s.setXY(float(p[0]), float(p[1]))
            s.setYaw(float(rng.uniform(-math.pi, math.pi)))
        states.append(s)
    return states


def _patch(kind: str, space: str, si: ob.SpaceInformation, make: Callable[[], NativePatch],
           agrees: Callable[[NativePatch], bool]) -> NativePatch | None:  # fmt: skip
    """Make a patched object once its space's checks pass; None (and one warning) otherwise."""
    key = f"{kind} {space}"
    if kind not in _enabled or space not in SPACES:
        return None
    with _lock:
        verdict = _verdicts.get(key)
    if verdict:
        return None
    try:
        if verdict is None and not _state_layout_ok(space, si):
            raise RuntimeError(f"{space} states are not laid out as expected")
        patch = make()
        if verdict is None and not agrees(patch):
            patch.release()
            raise RuntimeError(f"the compiled {kind} of {space} disagrees with the Python one")
    except RuntimeError as exc:
        with _lock:
            _verdicts[key] = str(exc)
        log.warning("compiled %s off for %s, using the Python one: %s", kind, space, exc)
        return None
    with _lock:
        _verdicts[key] = ""
    return patch


def _function(role: str, space: str) -> int:
    """Address of the compiled function of ``role`` for ``space`` (compiled or loaded on first use)."""
    from planning._native_kernels import FUNCTIONS

    return int(FUNCTIONS[role][space].address)


def native_objective(
    si: ob.SpaceInformation, grid: PackedGrid, space: str, reference: ob.OptimizationObjective
) -> NativePatch | None:
    """A ``PathLengthOptimizationObjective`` whose ``motionCost`` is the compiled risk cost.

    Its heuristic becomes the class's own ``motionCost`` (the length), since the class's
    heuristic calls ``motionCost`` and would overestimate. ``reference`` is the Python
    objective it must agree with, bit for bit (checked once per process and space).
    """

    def make() -> NativePatch:
        obj = ob.PathLengthOptimizationObjective(si)
        this = _cpp_address(obj, inline=True)
        if this is None:
            raise RuntimeError("nanobind does not store the objective inline")
        return NativePatch(obj, this, grid, {"cost": _function("cost", space), "heuristic": "cost"})

    def agrees(patch: NativePatch) -> bool:
        states = _random_states(si, grid, space, 2 * _CHECKS, 0.0)
        return all(patch.obj.motionCost(a, b).value() == reference.motionCost(a, b).value()
                   for a, b in zip(states[::2], states[1::2]))  # fmt: skip

    return _patch("objective", space, si, make, agrees)


def native_validity(
    si: ob.SpaceInformation, grid: PackedGrid, space: str, reference: Callable[[], Callable[[Any], bool]]
) -> NativePatch | None:
    """A state validity checker whose ``isValid`` is the compiled cell lookup (set it on ``si``).

    ``reference()`` makes the Python checker it must agree with, on states in and around the
    map (called on the first check only).
    """

    def make() -> NativePatch:
        obj = ob.AllValidStateValidityChecker(si)
        this = _cpp_address(obj, inline=True)
        if this is None:
            raise RuntimeError("nanobind does not store the validity checker inline")
        return NativePatch(obj, this, grid, {"valid": _function("valid", space)})

    def agrees(patch: NativePatch) -> bool:
        states = _random_states(si, grid, space, 4 * _CHECKS, 0.1)
        python = reference()
        return all(bool(patch.obj.isValid(s)) == bool(python(s)) for s in states)

    return _patch("validity", space, si, make, agrees)


def native_motion(
    si: ob.SpaceInformation, grid: PackedGrid, space: str, reference: Callable[[Any, Any], bool]
) -> NativePatch | None:
    """The set-up ``si``'s own ``DiscreteMotionValidator`` with its checks compiled (the cell walk).

    Call after ``si.setup()`` with no motion validator set. The ``lastValid`` overload answers
    like the plain one and leaves ``lastValid`` alone, as OMPL 2.0.1's bindings do for a Python
    validator. ``reference`` is the Python check it must agree with.
    """

    def make() -> NativePatch:
        obj = si.getMotionValidator()
        this = _cpp_address(obj, inline=False)
        if this is None:
            raise RuntimeError("the space's motion validator could not be located")
        return NativePatch(obj, this, grid, {r: _function(r, space) for r in ("check", "check_last")})

    def agrees(patch: NativePatch) -> bool:
        states = _random_states(si, grid, space, 2 * _CHECKS, 0.0)
        return all(bool(patch.obj.checkMotion(a, b)) == bool(reference(a, b)) for a, b in zip(states[::2], states[1::2]))

    return _patch("motion", space, si, make, agrees)
