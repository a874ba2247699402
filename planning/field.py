"""The risk field a planner sees: a risk grid, its observed mask, and their dilation by the robot.

Conventions (shared with ``fuzzyocc``): array index ``[i, j(, k)]`` runs along x, y(, z);
``origin`` is the corner of cell 0; cell ``c`` covers ``[origin + c * res, origin + (c + 1) * res)``
on each axis, and the map is the union of its cells (half-open at the upper bound).

Footprint rule (conservative, exact at cell resolution): the robot is an open disk (a ball
in 3-D) of radius ``robot_radius`` around its position. The dilated risk of cell ``q`` is the
largest risk of every cell ``c`` the footprint can overlap from *some* position in the closed
cell ``q``: ``c == q`` or ``gap(q, c) < robot_radius``, where ``gap`` is the distance between
the two closed squares (cubes), ``res * sqrt(sum(max(|q - c| - 1, 0) ** 2))``. So the dilated
risk of any cell whose closure holds a position bounds the worst cell under the footprint
there, wherever in the cell the robot stands: a check at cell resolution needs no sampling
margin. Cells outside the map count as never observed with risk 0.5 (unknown), so a footprint
hanging over the map's edge sees unknown space.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

UNKNOWN_RISK = 0.5  # risk of never-observed space (and of space outside the map)
#: ``plan``'s and the service's default ``max_risk``: the exports' free threshold (cells with net free evidence)
DEFAULT_MAX_RISK = 0.45


def footprint_reach(robot_radius: float, resolution: float) -> int:
    """Cells the footprint reaches from its centre cell along an axis: a cell's dilated value depends on no
    cell farther."""
    return int(math.floor(robot_radius / resolution)) + 1


def footprint(robot_radius: float, resolution: float, ndim: int) -> np.ndarray:
    """Cells whose risk a robot standing somewhere in the centre cell can overlap.

    Parameters
    ----------
    robot_radius : float
        Radius of the robot's disk (2-D) or ball (3-D), metres, >= 0.
    resolution : float
        Cell size, metres.
    ndim : int
        2 or 3.

    Returns
    -------
    bool array, shape (2 m + 1,) * ndim
        True for the offsets ``d`` with ``d == 0`` or ``gap(d) < robot_radius``.
    """
    rc = robot_radius / resolution
    m = footprint_reach(robot_radius, resolution)
    axes = np.meshgrid(*([np.arange(-m, m + 1)] * ndim), indexing="ij")
    gap2 = sum(np.maximum(np.abs(a) - 1, 0) ** 2 for a in axes)
    fp = gap2 < rc * rc
    fp[(m,) * ndim] = True
    return fp


def _boxes(fp: np.ndarray) -> list[tuple[int, ...]]:
    """Half-extents of axis-aligned boxes whose union is the (box-convex, symmetric) footprint."""
    m = fp.shape[0] // 2
    quadrant = fp[(slice(m, None),) * fp.ndim]  # offsets >= 0 on every axis
    boxes = []
    for corner in zip(*np.nonzero(quadrant), strict=True):
        # a box is needed only when no larger box in the quadrant contains it
        grown = False
        for axis in range(fp.ndim):
            bigger = list(corner)
            bigger[axis] += 1
            if bigger[axis] <= m and quadrant[tuple(bigger)]:
                grown = True
                break
        if not grown:
            boxes.append(tuple(int(c) for c in corner))
    return boxes


def box_max(values: np.ndarray, halves: Sequence[int], cval: float) -> np.ndarray:
    """Maximum of ``values`` over the box of ``2 h + 1`` cells along each axis around each cell.

    Cells beyond the array count as ``cval``: ``ndimage.maximum_filter(values, size=[2 h + 1, ...],
    mode="constant", cval=cval)`` bit for bit, a maximum rounding nothing (tests/planning/test_box_max.py).

    Parameters
    ----------
    values : float32 or uint8 array, 2-D or more (another dtype compiles a kernel of its own)
    halves : sequence of int >= 0
        Half-width ``h`` of the box along each axis.
    cval : float
        Value of the cells beyond the array (cast to the dtype).
    """
    src = np.ascontiguousarray(values)
    if src.ndim < 2 or len(halves) != src.ndim or min(halves) < 0:
        raise ValueError(f"box_max: {src.ndim}-D values need {src.ndim} half-widths >= 0, got {tuple(halves)}")
    out = np.empty_like(src)
    _box_max(src, halves, src.dtype.type(cval), out, False)
    return out


def _box_max(src: np.ndarray, halves: Sequence[int], fill: Any, out: np.ndarray, accumulate: bool) -> None:
    """``box_max`` of C-ordered ``src`` into ``out``; with ``accumulate``, the larger of it and ``out``.

    One pass over the last two axes, then one along each axis before them
    (``_dilation_kernels.box_max_2d``), each costing the same whatever the box's size.
    """
    shape = src.shape
    passes = []  # (outer, n, m, half along n, half along m) of (outer, n, m) views
    if halves[-2] or halves[-1]:
        passes.append((math.prod(shape[:-2]), shape[-2], shape[-1], halves[-2], halves[-1]))
    for axis in range(src.ndim - 2):
        if halves[axis]:
            passes.append((math.prod(shape[:axis]), shape[axis], math.prod(shape[axis + 1 :]), halves[axis], 0))
    if not passes:
        if accumulate:
            np.maximum(out, src, out=out)
        else:
            np.copyto(out, src)
        return
    # imported here: the web process imports this module but plans (and compiles kernels) only in workers
    from planning import _dilation_kernels

    # the passes between the first and the last go through one array, in place
    scratch = np.empty_like(src) if len(passes) > 1 else None
    for k, (outer, n, m, half_n, half_m) in enumerate(passes):
        final = k == len(passes) - 1
        dst = out if final else scratch
        assert dst is not None
        flat = src.reshape(-1)
        flat.flags.writeable = False  # a view: one compiled kernel per dtype, whether src is writable or not
        _dilation_kernels.box_max_2d(flat, outer, n, m, int(half_n), int(half_m), fill, dst.reshape(-1),
                                     final and accumulate)
        src = dst


def _dilate_max(values: np.ndarray, fp: np.ndarray, outside: float) -> np.ndarray:
    """Maximum of ``values`` under the footprint, the footprint's union of boxes at a time.

    Each box is a separable maximum filter (linear in the number of cells whatever its size),
    so the cost grows with the number of boxes (about the radius in cells in 2-D) and not with
    the footprint's area, as a generic ``grey_dilation`` with a footprint would.
    """
    src = np.ascontiguousarray(values)
    out = np.empty_like(src)
    for k, half in enumerate(_boxes(fp)):
        _box_max(src, half, src.dtype.type(outside), out, k > 0)
    return out


def _check_radius(robot_radius: float) -> float:
    value = float(robot_radius)
    if not math.isfinite(value) or value < 0.0:
        raise ValueError(f"robot_radius: must be a finite number >= 0, got {robot_radius!r}")
    return value


class RiskField:
    """A risk grid with resolution, origin and the mask of observed cells.

    Parameters
    ----------
    risk : (nx, ny) or (nx, ny, nz) array of float
        Risk per cell in [0, 1], along x, y(, z). Copied (float32) and made read-only.
    resolution : float
        Cell size in metres, > 0.
    origin : sequence of float
        World position of the corner of cell 0, one number per axis.
    observed : bool array of the same shape, optional
        Cells some beam touched; None means every cell was observed.

    Raises
    ------
    ValueError
        Naming the field: NaN or out-of-range risk, wrong ndim or shape, nonpositive
        resolution, origin of the wrong length.

    Notes
    -----
    Immutable after construction; dilations are computed lazily per robot radius and cached
    (the cache is not pickled, so a field sent to a worker process stays small).
    """

    __slots__ = ("_risk", "_observed", "_resolution", "_origin", "_cache")

    def __init__(
        self,
        risk: Any,
        resolution: float,
        origin: Sequence[float],
        observed: Any | None = None,
    ) -> None:
        try:
            arr = np.array(risk, dtype=np.float32)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"risk: not a numeric array ({exc})") from None
        if arr.ndim not in (2, 3):
            raise ValueError(f"risk: must be a 2-D or 3-D array, got {arr.ndim}-D")
        if arr.size == 0:
            raise ValueError(f"risk: must have at least one cell, got shape {arr.shape}")
        if not np.isfinite(arr).all():
            raise ValueError("risk: contains NaN or infinite values")
        if arr.min() < 0.0 or arr.max() > 1.0:
            raise ValueError(f"risk: values must lie in [0, 1], got [{arr.min()}, {arr.max()}]")
        try:
            res = float(resolution)
        except (TypeError, ValueError):
            raise ValueError(f"resolution: must be a number, got {resolution!r}") from None
        if not math.isfinite(res) or res <= 0.0:
            raise ValueError(f"resolution: must be a finite number > 0, got {resolution!r}")
        try:
            org = tuple(float(v) for v in origin)
        except (TypeError, ValueError):
            raise ValueError(f"origin: must be a sequence of {arr.ndim} numbers, got {origin!r}") from None
        if len(org) != arr.ndim or not all(math.isfinite(v) for v in org):
            raise ValueError(f"origin: must be {arr.ndim} finite numbers for a {arr.ndim}-D risk, got {origin!r}")
        if observed is None:
            obs = np.ones(arr.shape, dtype=bool)
        else:
            obs = np.asarray(observed)
            if obs.dtype != np.bool_:
                raise ValueError(f"observed: must be a bool array, got dtype {obs.dtype}")
            if obs.shape != arr.shape:
                raise ValueError(f"observed: shape {obs.shape} differs from risk shape {arr.shape}")
            obs = obs.copy()
        arr.setflags(write=False)
        obs.setflags(write=False)
        self._risk = arr
        self._observed = obs
        self._resolution = res
        self._origin = org
        self._cache: dict[tuple[str, float], np.ndarray] = {}

    # ------------------------------------------------------------ pickling (no cache)

    def __getstate__(self) -> dict[str, Any]:
        return {"risk": self._risk, "observed": self._observed, "resolution": self._resolution, "origin": self._origin}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self._risk = state["risk"]
        self._observed = state["observed"]
        self._resolution = state["resolution"]
        self._origin = state["origin"]
        self._cache = {}

    def __repr__(self) -> str:
        return f"RiskField(shape={self.shape}, resolution={self._resolution}, origin={self._origin})"

    # ------------------------------------------------------------ geometry

    @property
    def risk(self) -> np.ndarray:
        """Risk per cell, float32, read-only."""
        return self._risk

    @property
    def observed(self) -> np.ndarray:
        """Observed cells, bool, read-only."""
        return self._observed

    @property
    def resolution(self) -> float:
        return self._resolution

    @property
    def origin(self) -> tuple[float, ...]:
        return self._origin

    @property
    def ndim(self) -> int:
        return self._risk.ndim

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self._risk.shape)

    @property
    def upper(self) -> tuple[float, ...]:
        """World position of the far corner of the last cell (exclusive bound of the map)."""
        return tuple(o + n * self._resolution for o, n in zip(self._origin, self.shape, strict=True))

    def cell_of(self, points: Any) -> tuple[np.ndarray, np.ndarray]:
        """Cell indices of world points.

        Parameters
        ----------
        points : (M, ndim) array of float

        Returns
        -------
        index : (M, ndim) int64 array
            Cell indices, clipped into the grid (meaningful only where ``inside``).
        inside : (M,) bool array
            Points inside the map (half-open at the upper bound).
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, self.ndim)
        u = (pts - np.asarray(self._origin)) / self._resolution
        idx = np.floor(u)
        shape = np.asarray(self.shape)
        inside = np.isfinite(u).all(axis=1) & (idx >= 0).all(axis=1) & (idx < shape).all(axis=1)
        idx = np.clip(np.nan_to_num(idx), 0, shape - 1).astype(np.int64)
        return idx, inside

    # ------------------------------------------------------------ dilation and validity

    def _dilated(self, kind: str, robot_radius: float) -> np.ndarray:
        radius = _check_radius(robot_radius)
        hit = self._cache.get((kind, radius))
        if hit is None:
            fp = footprint(radius, self._resolution, self.ndim)
            if kind == "risk":
                hit = _dilate_max(self._risk, fp, UNKNOWN_RISK)
            elif kind == "observed_risk":  # never-observed cells (and the outside) are allow_unknown's to bound
                hit = _dilate_max(np.where(self._observed, self._risk, np.float32(0.0)), fp, 0.0)
            else:
                hit = _dilate_max((~self._observed).view(np.uint8), fp, 1).view(bool)  # 0 or 1
            hit.setflags(write=False)
            self._cache[(kind, radius)] = hit
        return hit

    def dilated_risk(self, robot_radius: float) -> np.ndarray:
        """Worst risk under the robot's footprint from anywhere in each cell (float32, read-only).

        Raises
        ------
        ValueError
            ``robot_radius`` negative or not finite.
        """
        return self._dilated("risk", robot_radius)

    def dilated_unknown(self, robot_radius: float) -> np.ndarray:
        """Cells from which the footprint can overlap never-observed space or leave the map."""
        return self._dilated("unknown", robot_radius)

    def dilated_observed_risk(self, robot_radius: float) -> np.ndarray:
        """Worst risk of the observed cells under the footprint (never-observed cells count 0)."""
        return self._dilated("observed_risk", robot_radius)

    def valid_mask(self, robot_radius: float, max_risk: float, allow_unknown: bool = True) -> np.ndarray:
        """Cells where every position is valid: no observed cell under the footprint above ``max_risk``,
        and, unless ``allow_unknown``, no never-observed cell (nor the outside of the map) under it.

        ``max_risk`` bounds what the sensor saw, ``allow_unknown`` what it never saw: an observed cell at
        risk 0.5 is mostly evidence for and against a surface that cancels out (a surface hit once and
        seen through twice), otherwise a cell just behind a surface, not the absence of evidence; the
        default ``max_risk`` 0.45 keeps the robot off it while unknown space stays open (docs/DESIGN.md
        section 5).

        Raises
        ------
        ValueError
            ``robot_radius`` negative or not finite, ``max_risk`` outside [0, 1].
        """
        limit = float(max_risk)
        if not (0.0 <= limit <= 1.0):
            raise ValueError(f"max_risk: must lie in [0, 1], got {max_risk!r}")
        # compared in float64, as the planners report risk, so a path's reported risk over observed cells never
        # exceeds it
        valid = self.dilated_observed_risk(robot_radius).astype(np.float64) <= limit
        if not allow_unknown:
            valid &= ~self.dilated_unknown(robot_radius)
        return valid
