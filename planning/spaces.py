"""OMPL state spaces over a packed grid: bounds, validity, motion checks and the risk objective.

Each state space comes with the three callbacks OMPL calls from C++:

- a state validity checker, plain Python over a flat list (about 1 M calls/s);
- a motion validator: for spaces whose motions are straight in position (R2, SE2, R3), the
  compiled cell walk of ``_segment_kernels`` (exact, every crossed cell, no sampling); for Dubins,
  the same walk over quarter-cell chords of the curve (compiled); for Reeds-Shepp, OMPL's
  own validator, which checks poses a quarter cell apart, each through the Python checker,
  against the valid mask eroded by one cell, so that what lies between two poses (within a
  quarter cell of the first) is valid too;
- the objective, a ``PathLengthOptimizationObjective`` whose ``motionCost`` is
  ``length + risk_weight * integral of risk``. Subclassing the path-length objective keeps
  its C++ cost-to-go and its direct informed sampler (the ellipse of length <= best cost),
  both admissible here because every motion costs at least its length;
  ``motionCostHeuristic`` is overridden back to plain length, because the parent's calls
  ``motionCost`` and would then overestimate.

For R2, SE2, Dubins and R3, the three are compiled into OMPL (``native.py``: same kernels, no
Python call per state or edge); the Python versions here are their reference and fallback.

Costs are defined on the position trace only (the heading of SE2 costs nothing; see
``_build_se2``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from ompl import base as ob

from planning import _dubins_kernels, _segment_kernels
from planning.native import NativePatch, native_motion, native_objective, native_validity
from planning.packed import PackedGrid, entry
from planning.planners import STATE_SPACE_NAMES

_Cost = ob.Cost
_sqrt = math.sqrt
_cost_2d = entry(_segment_kernels.segment_cost_2d)
_free_2d = entry(_segment_kernels.segment_free_2d)
_cost_3d = entry(_segment_kernels.segment_cost_3d)
_free_3d = entry(_segment_kernels.segment_free_3d)
_dubins_cost = entry(_dubins_kernels.dubins_cost)
_dubins_free = entry(_dubins_kernels.dubins_free)
_dubins_length = entry(_dubins_kernels.dubins_length)

# OMPL's Reeds-Shepp validator checks poses this far apart, in cells (the Dubins kernel cuts
# its curves into chords of the same length)
CURVE_CHECK_CELLS = 0.25


# ---------------------------------------------------------------- objectives


class RiskCostR2(ob.PathLengthOptimizationObjective):
    """Exact ``length * (1 + w * mean risk)`` of straight motions in the plane (R2 states)."""

    __slots__ = ("address",)  # a slot is quicker to read than an instance dict, per call

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.address = grid.address

    def motionCost(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802 - OMPL's name
        return _Cost(_cost_2d(self.address, s1[0], s1[1], s2[0], s2[1]))

    def motionCostHeuristic(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        dx = s1[0] - s2[0]
        dy = s1[1] - s2[1]
        return _Cost(_sqrt(dx * dx + dy * dy))


class RiskCostSE2(ob.PathLengthOptimizationObjective):
    """As :class:`RiskCostR2` on the x, y of SE2 states (SE2 interpolates x, y linearly)."""

    __slots__ = ("address",)  # a slot is quicker to read than an instance dict, per call

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.address = grid.address

    def motionCost(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        return _Cost(_cost_2d(self.address, s1.getX(), s1.getY(), s2.getX(), s2.getY()))

    def motionCostHeuristic(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        dx = s1.getX() - s2.getX()
        dy = s1.getY() - s2.getY()
        return _Cost(_sqrt(dx * dx + dy * dy))


class RiskCostR3(ob.PathLengthOptimizationObjective):
    """Exact ``length * (1 + w * mean risk)`` of straight motions in R3."""

    __slots__ = ("address",)  # a slot is quicker to read than an instance dict, per call

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.address = grid.address

    def motionCost(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        return _Cost(_cost_3d(self.address, s1[0], s1[1], s1[2], s2[0], s2[1], s2[2]))

    def motionCostHeuristic(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        dx = s1[0] - s2[0]
        dy = s1[1] - s2[1]
        dz = s1[2] - s2[2]
        return _Cost(_sqrt(dx * dx + dy * dy + dz * dz))


class RiskCostDubins(ob.PathLengthOptimizationObjective):
    """``length + w * risk integral`` along Dubins curves, computed by the compiled kernel.

    The kernel finds the same shortest Dubins word as OMPL (checked against OMPL's distance
    and interpolation in the tests) and sums the risk at one midpoint per cell of length.
    """

    __slots__ = ("address",)

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.address = grid.address

    def motionCost(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        return _Cost(_dubins_cost(self.address, s1.getX(), s1.getY(), s1.getYaw(), s2.getX(), s2.getY(), s2.getYaw()))

    def motionCostHeuristic(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        return _Cost(
            _dubins_length(self.address, s1.getX(), s1.getY(), s1.getYaw(), s2.getX(), s2.getY(), s2.getYaw())
        )


class RiskCostCurve(ob.PathLengthOptimizationObjective):
    """``length + w * risk integral`` along Reeds-Shepp curves.

    The curve's length is OMPL's distance; the integral is a midpoint sum with one sample
    per cell of length, each sample a call to the space's ``interpolate`` (the curve's
    segments are not exposed by the bindings): about 150 times slower than the Dubins kernel.
    """

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.space = si.getStateSpace()
        self.scratch = si.allocState()
        self.risk_flat: list[float] = grid.risk.astype(float).reshape(-1).tolist()
        self.weight = grid.risk_weight
        self.inv = 1.0 / grid.resolution
        self.ox, self.oy = grid.origin
        self.nx, self.ny = grid.shape

    def motionCost(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        length = self.space.distance(s1, s2)
        if self.weight == 0.0 or length == 0.0:
            return _Cost(length)
        n = int(length * self.inv) + 1
        interpolate = self.space.interpolate
        tmp = self.scratch
        risk = self.risk_flat
        inv, ox, oy, nx, ny = self.inv, self.ox, self.oy, self.nx, self.ny
        acc = 0.0
        for step in range(n):
            interpolate(s1, s2, (step + 0.5) / n, tmp)
            i = min(max(int((tmp.getX() - ox) * inv), 0), nx - 1)
            j = min(max(int((tmp.getY() - oy) * inv), 0), ny - 1)
            acc += risk[i * ny + j]
        return _Cost(length * (1.0 + self.weight * acc / n))

    def motionCostHeuristic(self, s1: Any, s2: Any) -> ob.Cost:  # noqa: N802
        return _Cost(self.space.distance(s1, s2))


# ---------------------------------------------------------------- motion validators


class StraightMotionR2(ob.MotionValidator):
    """Exact motion check for R2 states: every cell the segment crosses must be valid."""

    __slots__ = ("address",)  # a slot is quicker to read than an instance dict, per call

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.address = grid.address

    def checkMotion(self, s1: Any, s2: Any) -> bool:  # noqa: N802
        return _free_2d(self.address, s1[0], s1[1], s2[0], s2[1])


class StraightMotionSE2(ob.MotionValidator):
    """Exact motion check on the x, y of SE2 states."""

    __slots__ = ("address",)  # a slot is quicker to read than an instance dict, per call

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.address = grid.address

    def checkMotion(self, s1: Any, s2: Any) -> bool:  # noqa: N802
        return _free_2d(self.address, s1.getX(), s1.getY(), s2.getX(), s2.getY())


class DubinsMotion(ob.MotionValidator):
    """Every cell crossed by the Dubins curve, cut in quarter-cell chords (compiled)."""

    __slots__ = ("address",)

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.address = grid.address

    def checkMotion(self, s1: Any, s2: Any) -> bool:  # noqa: N802
        return _dubins_free(self.address, s1.getX(), s1.getY(), s1.getYaw(), s2.getX(), s2.getY(), s2.getYaw())


class StraightMotionR3(ob.MotionValidator):
    """Exact motion check for R3 states."""

    __slots__ = ("address",)  # a slot is quicker to read than an instance dict, per call

    def __init__(self, si: ob.SpaceInformation, grid: PackedGrid) -> None:
        super().__init__(si)
        self.address = grid.address

    def checkMotion(self, s1: Any, s2: Any) -> bool:  # noqa: N802
        return _free_3d(self.address, s1[0], s1[1], s1[2], s2[0], s2[1], s2[2])


# ---------------------------------------------------------------- state validity


def _validity_2d(grid: PackedGrid, se2: bool, valid: list[bool] | None = None) -> Callable[[Any], bool]:
    valid = grid.valid_flat if valid is None else valid
    ox, oy = grid.origin
    nx, ny = grid.shape
    inv = 1.0 / grid.resolution
    if not se2:

        def is_valid(s: Any) -> bool:
            u = (s[0] - ox) * inv
            v = (s[1] - oy) * inv
            if u < 0.0 or v < 0.0 or u >= nx or v >= ny:
                return False
            return valid[int(u) * ny + int(v)]

    else:

        def is_valid(s: Any) -> bool:
            u = (s.getX() - ox) * inv
            v = (s.getY() - oy) * inv
            if u < 0.0 or v < 0.0 or u >= nx or v >= ny:
                return False
            return valid[int(u) * ny + int(v)]

    return is_valid


def _validity_3d(grid: PackedGrid) -> Callable[[Any], bool]:
    valid = grid.valid_flat
    ox, oy, oz = grid.origin
    nx, ny, nz = grid.shape
    inv = 1.0 / grid.resolution

    def is_valid(s: Any) -> bool:
        u = (s[0] - ox) * inv
        v = (s[1] - oy) * inv
        w = (s[2] - oz) * inv
        if u < 0.0 or v < 0.0 or w < 0.0 or u >= nx or v >= ny or w >= nz:
            return False
        return valid[(int(u) * ny + int(v)) * nz + int(w)]

    return is_valid


# ---------------------------------------------------------------- spaces


@dataclass
class OmplSpace:
    """A set-up SpaceInformation and how to move states in and out of it."""

    si: ob.SpaceInformation
    objective: ob.OptimizationObjective
    to_state: Callable[[Sequence[float]], Any]
    values: Callable[[Any], tuple[float, ...]]
    keepalive: tuple[Any, ...]  # Python objects C++ holds by reference
    native: tuple[NativePatch, ...] = ()  # the compiled checks and objective in use

    def close(self) -> None:
        """Release the compiled objects once the planner and problem are done with them."""
        for patch in self.native:
            patch.release()


def _set_checks(
    si: ob.SpaceInformation,
    grid: PackedGrid,
    name: str,
    make_checker: Callable[[], Callable[[Any], bool]],
    motion: type | None,
) -> tuple[list[NativePatch], tuple[Any, ...]]:
    """Set ``si``'s validity checker and motion validator, compiled where they pass their checks
    (``native.py``), and set ``si`` up. ``motion`` None means OMPL's Reeds-Shepp validator.
    The Python checker is made only when needed (its flat list costs 8 bytes a cell).

    Returns the compiled objects in use and the Python ones C++ holds by reference.
    """
    patches: list[NativePatch] = []
    fast = native_validity(si, grid, name, make_checker) if motion is not None else None
    checker = None
    if fast is not None:
        si.setStateValidityChecker(fast.obj)
        patches.append(fast)
    else:
        checker = make_checker()
        si.setStateValidityChecker(checker)
    if motion is None:
        validator: Any = ob.ReedsSheppMotionValidator(si)
        si.setMotionValidator(validator)
        _finish(si, grid)
        return patches, (checker, validator)
    _finish(si, grid)  # with OMPL's default motion validator, which native_motion compiles
    python = motion(si, grid)
    moves = native_motion(si, grid, name, python.checkMotion)
    if moves is not None:
        patches.append(moves)
        return patches, ()
    si.setMotionValidator(python)
    si.setup()
    return patches, (checker, python)


def _risk_objective(
    si: ob.SpaceInformation, grid: PackedGrid, name: str, python: ob.OptimizationObjective, patches: list[NativePatch]
) -> ob.OptimizationObjective:
    """The compiled objective where it passes its checks (``native.py``), else the Python one."""
    fast = native_objective(si, grid, name, python)
    if fast is None:
        return python
    patches.append(fast)
    return fast.obj


@dataclass(frozen=True)
class SpaceSpec:
    """A state space by name: the field dimension it needs and its state layout."""

    name: str
    field_ndim: int
    state_dim: int  # numbers per state: 2 (R2), 3 (x, y, theta or x, y, z)
    curved: bool  # motions follow turning-radius curves
    build: Callable[[PackedGrid, float | None], OmplSpace]
    rate_factor: float = 1.0  # planner iterations per second relative to R2 (seeded budgets)


def wrap_angle(theta: float) -> float:
    """An angle in [-pi, pi)."""
    return (theta + math.pi) % (2.0 * math.pi) - math.pi


def _bounds(grid: PackedGrid, axes: int) -> ob.RealVectorBounds:
    bounds = ob.RealVectorBounds(axes)
    # states must stay inside the half-open map: sample a hair inside the upper edge
    margin = 1e-6 * grid.resolution
    for axis in range(axes):
        bounds.setLow(axis, grid.origin[axis])
        bounds.setHigh(axis, grid.origin[axis] + grid.shape[axis] * grid.resolution - margin)
    return bounds


def _finish(si: ob.SpaceInformation, grid: PackedGrid) -> None:
    space = si.getStateSpace()
    si.setStateValidityCheckingResolution(CURVE_CHECK_CELLS * grid.resolution / space.getMaximumExtent())
    si.setup()


def _build_r2(grid: PackedGrid, turning_radius: float | None) -> OmplSpace:
    space = ob.RealVectorStateSpace(2)
    space.setBounds(_bounds(grid, 2))
    si = ob.SpaceInformation(space)
    patches, keep = _set_checks(si, grid, "R2", lambda: _validity_2d(grid, se2=False), StraightMotionR2)

    def to_state(v: Sequence[float]) -> Any:
        s = si.allocState()
        s[0], s[1] = float(v[0]), float(v[1])
        return s

    objective = _risk_objective(si, grid, "R2", RiskCostR2(si, grid), patches)
    return OmplSpace(si, objective, to_state, lambda s: (s[0], s[1]), (space, *keep), tuple(patches))


def _se2_like(space: ob.SE2StateSpace, grid: PackedGrid, straight: bool) -> OmplSpace:
    space.setBounds(_bounds(grid, 2))
    si = ob.SpaceInformation(space)
    dubins = isinstance(space, ob.DubinsStateSpace)
    # Reeds-Shepp motions are checked pose by pose by OMPL: against the eroded mask (module docstring)
    def make_checker() -> Callable[[Any], bool]:
        return _validity_2d(grid, se2=True, valid=None if straight or dubins else grid.eroded_valid_flat())

    name = "SE2" if straight else "Dubins" if dubins else "ReedsShepp"
    motion = StraightMotionSE2 if straight else DubinsMotion if dubins else None
    patches, keep = _set_checks(si, grid, name, make_checker, motion)
    objective: ob.OptimizationObjective
    if straight:
        objective = _risk_objective(si, grid, name, RiskCostSE2(si, grid), patches)
    elif dubins:
        objective = _risk_objective(si, grid, name, RiskCostDubins(si, grid), patches)
    else:
        objective = RiskCostCurve(si, grid)  # needs OMPL's interpolation: stays in Python

    def to_state(v: Sequence[float]) -> Any:
        s = si.allocState()
        s.setXY(float(v[0]), float(v[1]))
        s.setYaw(wrap_angle(float(v[2])))  # OMPL's SO2 bounds are [-pi, pi): pi itself is out
        return s

    return OmplSpace(
        si, objective, to_state, lambda s: (s.getX(), s.getY(), s.getYaw()), (space, *keep), tuple(patches)
    )


def _build_se2(grid: PackedGrid, turning_radius: float | None) -> OmplSpace:
    space = ob.SE2StateSpace()
    # Plain SE2 is a holonomic robot with a heading: the cost is position-only and the disk
    # footprint ignores heading, so the metric ignores it too. That keeps the path-length
    # cost-to-go and informed sampler admissible (with OMPL's default weight of 0.5 on the
    # heading they would overestimate), and a goal is reached by position; plan() then turns
    # the heading steadily from the start's to the goal's along the path.
    space.setSubspaceWeight(1, 0.0)
    return _se2_like(space, grid, straight=True)


def _build_dubins(grid: PackedGrid, turning_radius: float | None) -> OmplSpace:
    assert turning_radius is not None
    return _se2_like(ob.DubinsStateSpace(turningRadius=turning_radius), grid, straight=False)


def _build_reeds_shepp(grid: PackedGrid, turning_radius: float | None) -> OmplSpace:
    assert turning_radius is not None
    return _se2_like(ob.ReedsSheppStateSpace(turningRadius=turning_radius), grid, straight=False)


def _build_r3(grid: PackedGrid, turning_radius: float | None) -> OmplSpace:
    space = ob.RealVectorStateSpace(3)
    space.setBounds(_bounds(grid, 3))
    si = ob.SpaceInformation(space)
    patches, keep = _set_checks(si, grid, "R3", lambda: _validity_3d(grid), StraightMotionR3)

    def to_state(v: Sequence[float]) -> Any:
        s = si.allocState()
        s[0], s[1], s[2] = float(v[0]), float(v[1]), float(v[2])
        return s

    objective = _risk_objective(si, grid, "R3", RiskCostR3(si, grid), patches)
    return OmplSpace(si, objective, to_state, lambda s: (s[0], s[1], s[2]), (space, *keep), tuple(patches))


STATE_SPACES: dict[str, SpaceSpec] = {
    "R2": SpaceSpec("R2", field_ndim=2, state_dim=2, curved=False, build=_build_r2),
    "SE2": SpaceSpec("SE2", field_ndim=2, state_dim=3, curved=False, build=_build_se2),
    "Dubins": SpaceSpec("Dubins", field_ndim=2, state_dim=3, curved=True, build=_build_dubins, rate_factor=0.25),
    "ReedsShepp": SpaceSpec(
        "ReedsShepp", field_ndim=2, state_dim=3, curved=True, build=_build_reeds_shepp, rate_factor=0.05
    ),
    "R3": SpaceSpec("R3", field_ndim=3, state_dim=3, curved=False, build=_build_r3),
}
if tuple(STATE_SPACES) != STATE_SPACE_NAMES:
    raise RuntimeError(f"planning.planners.STATE_SPACE_NAMES {STATE_SPACE_NAMES} differs from {tuple(STATE_SPACES)}")
