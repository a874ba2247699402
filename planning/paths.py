"""A found path made into what a plan hands out: polylines thinned, interpolated at the map's
resolution, and measured against the packed grid into a PlanResult (the grid and the OMPL planners alike)."""

from __future__ import annotations

import math
import time

import numpy as np

from planning.packed import PackedGrid
from planning.result import PlanResult
from planning.spaces import SpaceSpec


def interpolate_straight(points: np.ndarray, step: float) -> np.ndarray:
    """Points along a polyline no more than ``step`` apart, keeping every vertex (vectorized)."""
    if len(points) < 2:
        return points.copy()
    seg = np.diff(points, axis=0)
    pieces = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / step).astype(np.int64))
    owner = np.repeat(np.arange(len(seg)), pieces)
    starts = np.cumsum(pieces) - pieces
    frac = (np.arange(owner.size) - starts[owner]) / pieces[owner]
    out = points[owner] + frac[:, None] * seg[owner]
    return np.vstack([out, points[-1:]])


def drop_collinear(points: np.ndarray) -> np.ndarray:
    """Remove interior points where a polyline goes straight on (exact: same segments)."""
    if len(points) < 3:
        return points
    d = np.diff(points, axis=0)
    norms = np.linalg.norm(d, axis=1)
    keep_seg = norms > 0
    points = np.vstack([points[:1], points[1:][keep_seg]])
    if len(points) < 3:
        return points
    d = np.diff(points, axis=0)
    d /= np.linalg.norm(d, axis=1)[:, None]
    turn = np.linalg.norm(d[1:] - d[:-1], axis=1) > 1e-9
    return np.vstack([points[:1], points[1:-1][turn], points[-1:]])


def plan_result(
    grid: PackedGrid,
    sspec: SpaceSpec,
    planner: str,
    status: str,
    path: np.ndarray | None,
    measure_points: np.ndarray | None,
    t0: float,
    message: str = "",
    iterations: int = 0,
    first_solution_time: float | None = None,
    error_code: str = "",
    stopped_by: str = "complete",
) -> PlanResult:
    """The result of a plan started at ``t0``: ``path`` measured along ``measure_points`` (the polyline
    verified, which may be finer than the path), or an empty path when ``status`` is "none"."""
    if status == "none" or path is None or measure_points is None:
        nan = math.nan
        empty = np.zeros((0, sspec.state_dim))
        return PlanResult("none", empty, nan, nan, nan, nan, planner, sspec.name,
                          time.perf_counter() - t0, message, iterations, nan, error_code, stopped_by)  # fmt: skip
    m = grid.evaluate(measure_points[:, : grid.ndim])
    elapsed = time.perf_counter() - t0
    if m.length > 0:
        mean = m.integral / m.length
    else:
        mean = m.peak
    return PlanResult(
        status,  # type: ignore[arg-type]
        path,
        m.length,
        m.peak,
        mean,
        m.length + grid.risk_weight * m.integral,
        planner,
        sspec.name,
        elapsed,
        message,
        iterations,
        first_solution_time if first_solution_time is not None else elapsed,
        error_code,
        stopped_by,  # type: ignore[arg-type]
    )

