"""``motionCost`` with OMPL's C++ signature, compiled by numba (see ``native.py``).

Each function here is a C callable ``double (const void *self, const State *s1, const State *s2)``:
on x86-64 (System V) that is exactly how ``ompl::base::Cost motionCost(const State *, const
State *) const`` is called, because ``Cost`` is a single trivially copyable double, returned in
xmm0. The objective's packed grid is found through the object's own (private) virtual table,
in the word after its last copied slot.

State layouts, as OMPL 2.0 lays them out (every ``State`` starts with its vtable pointer):
``RealVectorStateSpace::StateType`` is ``{vptr, double *values}``; ``SE2StateSpace::StateType``
is a compound state ``{vptr, State **components}`` whose component 0 is a real vector (x, y)
and component 1 an ``SO2StateSpace::StateType`` ``{vptr, double value}`` (yaw). ``native.py``
checks these layouts on live states before any of this code runs.
"""

from __future__ import annotations

from numba import cfunc, njit, types
from numba.extending import intrinsic

from planning import _kernels

# slots of the class's virtual table copied into each private table; the grid address follows
COPIED_SLOTS = 48
GRID_SLOT = COPIED_SLOTS

MOTION_COST = types.float64(types.intp, types.intp, types.intp)


@intrinsic
def _i64_ptr(typingctx, address):  # type: ignore[no-untyped-def]
    """Reinterpret an integer address as ``int64*``."""
    sig = types.CPointer(types.int64)(types.intp)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.int64)))

    return sig, codegen


@njit(cache=True, inline="always")
def _grid(this: int) -> int:
    return _i64_ptr(_i64_ptr(this)[0])[GRID_SLOT]


@njit(cache=True, inline="always")
def _real(state: int):  # type: ignore[no-untyped-def]
    """``values`` of a real-vector state."""
    return _kernels._f64_ptr(_i64_ptr(state)[1])


@njit(cache=True, inline="always")
def _se2(state: int) -> tuple[float, float, float]:
    """x, y, yaw of an SE2 (or Dubins / Reeds-Shepp) state."""
    components = _i64_ptr(_i64_ptr(state)[1])
    xy = _real(components[0])
    yaw = _kernels._f64_ptr(components[1])[1]
    return xy[0], xy[1], yaw


@cfunc(MOTION_COST, cache=True)
def cost_r2(this: int, s1: int, s2: int) -> float:
    a = _real(s1)
    b = _real(s2)
    return _kernels.segment_cost_2d(_grid(this), a[0], a[1], b[0], b[1])


@cfunc(MOTION_COST, cache=True)
def cost_r3(this: int, s1: int, s2: int) -> float:
    a = _real(s1)
    b = _real(s2)
    return _kernels.segment_cost_3d(_grid(this), a[0], a[1], a[2], b[0], b[1], b[2])


@cfunc(MOTION_COST, cache=True)
def cost_se2(this: int, s1: int, s2: int) -> float:
    x1, y1, _ = _se2(s1)
    x2, y2, _ = _se2(s2)
    return _kernels.segment_cost_2d(_grid(this), x1, y1, x2, y2)


@cfunc(MOTION_COST, cache=True)
def cost_dubins(this: int, s1: int, s2: int) -> float:
    x1, y1, t1 = _se2(s1)
    x2, y2, t2 = _se2(s2)
    return _kernels.dubins_cost(_grid(this), x1, y1, t1, x2, y2, t2)


COST_FUNCTIONS = {"R2": cost_r2, "R3": cost_r3, "SE2": cost_se2, "Dubins": cost_dubins}
