"""Shared helpers for the planning tests: small maps and an independent footprint check."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from planning import RiskField

RES = 0.05


def densify(path: np.ndarray, step: float) -> np.ndarray:
    """Points along a polyline no more than ``step`` apart (positions only)."""
    if len(path) < 2:
        return path.copy()
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(1, math.ceil(np.linalg.norm(b - a) / step))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def worst_under_footprint(field: RiskField, points: np.ndarray, radius: float) -> np.ndarray:
    """Largest raw risk among the cells an open disk (ball) of ``radius`` overlaps at each point.

    Written from the geometry, independently of the planner's dilation: a cell counts when
    the distance from the point to its square (cube) is below the radius, or it holds the
    point. Cells outside the map count as unknown (0.5), as documented.
    """
    nd = field.ndim
    res = field.resolution
    u = (points[:, :nd] - np.asarray(field.origin)) / res
    base = np.floor(u).astype(int)
    m = int(math.ceil(radius / res)) + 1
    offsets = np.stack(np.meshgrid(*([np.arange(-m, m + 1)] * nd), indexing="ij"), -1).reshape(-1, nd)
    cells = base[:, None, :] + offsets[None, :, :]
    gap = np.maximum(np.maximum(cells - u[:, None, :], u[:, None, :] - (cells + 1)), 0.0) * res
    under = ((gap**2).sum(-1) < radius**2) | (offsets == 0).all(-1)[None, :]
    shape = np.asarray(field.shape)
    inside = ((cells >= 0) & (cells < shape)).all(-1)
    clipped = np.clip(cells, 0, shape - 1)
    risk = np.where(inside, field.risk[tuple(clipped[..., a] for a in range(nd))], 0.5)
    return np.where(under, risk, 0.0).max(axis=1)


@pytest.fixture
def footprint_check() -> Callable[[RiskField, np.ndarray, float], float]:
    """Worst raw risk under the footprint along a path checked every tenth of a cell."""

    def check(field: RiskField, path: np.ndarray, radius: float) -> float:
        pts = densify(np.asarray(path, dtype=float)[:, : field.ndim], 0.1 * field.resolution)
        return float(worst_under_footprint(field, pts, radius).max())

    return check


def wall_with_door(n: int = 100, door_cells: int = 0, door_at: int = 50, thickness: int = 1) -> np.ndarray:
    """An n x n field, free, with a vertical wall at x = n / 2 and a door of ``door_cells`` in y."""
    risk = np.zeros((n, n), dtype=np.float32)
    x = n // 2
    risk[x : x + thickness, :] = 1.0
    if door_cells:
        lo = door_at - door_cells // 2
        risk[x : x + thickness, lo : lo + door_cells] = 0.0
    return risk


@pytest.fixture
def make_wall() -> Callable[..., np.ndarray]:
    return wall_with_door
