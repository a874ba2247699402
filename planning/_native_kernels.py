"""OMPL's per-state and per-edge virtual functions with their C++ signatures, compiled by numba.

See ``native.py``. On x86-64 (System V) a C function ``double f(void *self, const State *s1,
const State *s2)`` is called exactly as ``Cost OptimizationObjective::motionCost(const State *,
const State *) const`` (``Cost`` is one trivially copyable double, returned in xmm0), and a
``uint8_t f(void *self, ...)`` returning 0 or 1 as a member function returning ``bool``. An
object's packed grid is found through its own (private) virtual table, in the word after the
last copied slot.

State layouts, as OMPL 2.0 lays them out (every ``State`` starts with its vtable pointer):
``RealVectorStateSpace::StateType`` is ``{vptr, double *values}``; ``SE2StateSpace::StateType``
is a compound state ``{vptr, State **components}`` whose component 0 is a real vector (x, y)
and component 1 an ``SO2StateSpace::StateType`` ``{vptr, double value}`` (yaw). ``native.py``
checks these layouts on live states before any of this code runs.
"""

from __future__ import annotations

from numba import cfunc, njit, types

from planning._dubins_kernels import dubins_cost, dubins_free
from planning._segment_kernels import (
    H_INV_RES,
    H_NCELLS,
    H_ORIGIN,
    H_SHAPE,
    HEADER,
    f64_ptr,
    pointer_to,
    segment_cost_2d,
    segment_cost_3d,
    segment_free_2d,
    segment_free_3d,
)

# slots of the class's virtual table copied into each private table; the grid address follows
COPIED_SLOTS = 48
GRID_SLOT = COPIED_SLOTS

MOTION_COST = types.float64(types.intp, types.intp, types.intp)  # Cost motionCost(s1, s2) const
IS_VALID = types.uint8(types.intp, types.intp)  # bool isValid(state) const
CHECK_MOTION = types.uint8(types.intp, types.intp, types.intp)  # bool checkMotion(s1, s2) const
# bool checkMotion(s1, s2, std::pair<State *, double> &lastValid) const
CHECK_MOTION_LAST = types.uint8(types.intp, types.intp, types.intp, types.intp)


#: ``int64*`` at an integer address: the words of OMPL's objects and virtual tables.
_i64_ptr = pointer_to(types.int64)


@njit(cache=True, inline="always")
def _grid(this: int) -> int:
    return _i64_ptr(_i64_ptr(this)[0])[GRID_SLOT]


@njit(cache=True, inline="always")
def _real(state: int):  # type: ignore[no-untyped-def]
    """``values`` of a real-vector state."""
    return f64_ptr(_i64_ptr(state)[1])


@njit(cache=True, inline="always")
def _se2(state: int) -> tuple[float, float, float]:
    """x, y, yaw of an SE2 (or Dubins / Reeds-Shepp) state."""
    components = _i64_ptr(_i64_ptr(state)[1])
    xy = _real(components[0])
    yaw = f64_ptr(components[1])[1]
    return xy[0], xy[1], yaw


@cfunc(MOTION_COST, cache=True)
def cost_r2(this: int, s1: int, s2: int) -> float:
    a = _real(s1)
    b = _real(s2)
    return segment_cost_2d(_grid(this), a[0], a[1], b[0], b[1])


@cfunc(MOTION_COST, cache=True)
def cost_r3(this: int, s1: int, s2: int) -> float:
    a = _real(s1)
    b = _real(s2)
    return segment_cost_3d(_grid(this), a[0], a[1], a[2], b[0], b[1], b[2])


@cfunc(MOTION_COST, cache=True)
def cost_se2(this: int, s1: int, s2: int) -> float:
    x1, y1, _ = _se2(s1)
    x2, y2, _ = _se2(s2)
    return segment_cost_2d(_grid(this), x1, y1, x2, y2)


@cfunc(MOTION_COST, cache=True)
def cost_dubins(this: int, s1: int, s2: int) -> float:
    x1, y1, t1 = _se2(s1)
    x2, y2, t2 = _se2(s2)
    return dubins_cost(_grid(this), x1, y1, t1, x2, y2, t2)


@njit(cache=True, inline="always")
def _cell_valid(address: int, u: float, v: float, w: float) -> bool:
    """The packed valid flag of the cell holding grid coordinates (u, v, w); False outside."""
    ptr = f64_ptr(address)
    nx = ptr[H_SHAPE]
    ny = ptr[H_SHAPE + 1]
    nz = ptr[H_SHAPE + 2]
    if not (0.0 <= u < nx and 0.0 <= v < ny and 0.0 <= w < nz):  # NaN fails too
        return False
    index = (int(u) * int(ny) + int(v)) * int(nz) + int(w)
    return ptr[HEADER + int(ptr[H_NCELLS]) + index] != 0.0


@njit(cache=True, inline="always")
def _valid_xy(address: int, x: float, y: float) -> bool:
    ptr = f64_ptr(address)
    inv = ptr[H_INV_RES]
    return _cell_valid(address, (x - ptr[H_ORIGIN]) * inv, (y - ptr[H_ORIGIN + 1]) * inv, 0.0)


@cfunc(IS_VALID, cache=True)
def valid_r2(this: int, s: int) -> int:
    p = _real(s)
    return 1 if _valid_xy(_grid(this), p[0], p[1]) else 0


@cfunc(IS_VALID, cache=True)
def valid_se2(this: int, s: int) -> int:
    x, y, _ = _se2(s)
    return 1 if _valid_xy(_grid(this), x, y) else 0


@cfunc(IS_VALID, cache=True)
def valid_r3(this: int, s: int) -> int:
    p = _real(s)
    address = _grid(this)
    ptr = f64_ptr(address)
    inv = ptr[H_INV_RES]
    u = (p[0] - ptr[H_ORIGIN]) * inv
    v = (p[1] - ptr[H_ORIGIN + 1]) * inv
    w = (p[2] - ptr[H_ORIGIN + 2]) * inv
    return 1 if _cell_valid(address, u, v, w) else 0


@njit(cache=True, inline="always")
def _free_r2(this: int, s1: int, s2: int) -> int:
    a = _real(s1)
    b = _real(s2)
    return 1 if segment_free_2d(_grid(this), a[0], a[1], b[0], b[1]) else 0


@njit(cache=True, inline="always")
def _free_se2(this: int, s1: int, s2: int) -> int:
    x1, y1, _ = _se2(s1)
    x2, y2, _ = _se2(s2)
    return 1 if segment_free_2d(_grid(this), x1, y1, x2, y2) else 0


@njit(cache=True, inline="always")
def _free_dubins(this: int, s1: int, s2: int) -> int:
    x1, y1, t1 = _se2(s1)
    x2, y2, t2 = _se2(s2)
    return 1 if dubins_free(_grid(this), x1, y1, t1, x2, y2, t2) else 0


@njit(cache=True, inline="always")
def _free_r3(this: int, s1: int, s2: int) -> int:
    a = _real(s1)
    b = _real(s2)
    return 1 if segment_free_3d(_grid(this), a[0], a[1], a[2], b[0], b[1], b[2]) else 0


# The overload with ``lastValid`` answers like the plain one and leaves ``lastValid`` as the
# caller set it, which is what OMPL 2.0.1's bindings do for a Python MotionValidator: planners
# behave the same with the compiled validator and with the Python fallback.


@cfunc(CHECK_MOTION, cache=True)
def free_r2(this: int, s1: int, s2: int) -> int:
    return _free_r2(this, s1, s2)


@cfunc(CHECK_MOTION_LAST, cache=True)
def free_last_r2(this: int, s1: int, s2: int, last_valid: int) -> int:
    return _free_r2(this, s1, s2)


@cfunc(CHECK_MOTION, cache=True)
def free_se2(this: int, s1: int, s2: int) -> int:
    return _free_se2(this, s1, s2)


@cfunc(CHECK_MOTION_LAST, cache=True)
def free_last_se2(this: int, s1: int, s2: int, last_valid: int) -> int:
    return _free_se2(this, s1, s2)


@cfunc(CHECK_MOTION, cache=True)
def free_dubins(this: int, s1: int, s2: int) -> int:
    return _free_dubins(this, s1, s2)


@cfunc(CHECK_MOTION_LAST, cache=True)
def free_last_dubins(this: int, s1: int, s2: int, last_valid: int) -> int:
    return _free_dubins(this, s1, s2)


@cfunc(CHECK_MOTION, cache=True)
def free_r3(this: int, s1: int, s2: int) -> int:
    return _free_r3(this, s1, s2)


@cfunc(CHECK_MOTION_LAST, cache=True)
def free_last_r3(this: int, s1: int, s2: int, last_valid: int) -> int:
    return _free_r3(this, s1, s2)


# role -> state space -> compiled function
FUNCTIONS = {
    "cost": {"R2": cost_r2, "R3": cost_r3, "SE2": cost_se2, "Dubins": cost_dubins},
    "valid": {"R2": valid_r2, "R3": valid_r3, "SE2": valid_se2, "Dubins": valid_se2},
    "check": {"R2": free_r2, "R3": free_r3, "SE2": free_se2, "Dubins": free_dubins},
    "check_last": {"R2": free_last_r2, "R3": free_last_r3, "SE2": free_last_se2, "Dubins": free_last_dubins},
}
