"""One query's view of a field: dilated risk and validity packed for the compiled kernels."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from planning import _segment_kernels
from planning.field import RiskField, box_max


def entry(dispatcher: Any) -> Any:
    """The compiled function behind a numba dispatcher with one signature, without dispatch.

    Calling the entry point skips numba's type resolution (about 0.35 us of the 0.5 us a call
    costs from Python); the dispatcher itself is the fallback should numba move it.
    """
    try:
        return dispatcher.overloads[dispatcher.signatures[0]].entry_point
    except (AttributeError, IndexError, KeyError):  # pragma: no cover - numba internals moved
        return dispatcher


@dataclass(frozen=True)
class PathMeasures:
    """Measures of a polyline against a packed grid (see ``_segment_kernels.evaluate_polyline``)."""

    length: float
    integral: float
    peak: float
    first_bad_segment: int

    @property
    def valid(self) -> bool:
        return self.first_bad_segment < 0


class PackedGrid:
    """Dilated risk and validity of one query (robot radius, max_risk, allow_unknown, weight).

    Attributes
    ----------
    buffer : float64 array
        The packed grid (header, risk, valid); ``address`` points into it, so it lives as
        long as this object.
    valid_flat : list of bool
        Validity per cell in C order, for the plain-Python state validity checker (a list
        lookup is faster than any numpy call per state).
    endpoint_cells : tuple of int
        Flat indices of the start's and goal's cells, once ``plan`` has checked them.
    """

    def __init__(
        self,
        field: RiskField,
        robot_radius: float,
        max_risk: float,
        allow_unknown: bool,
        risk_weight: float,
        turning_radius: float | None = None,
    ) -> None:
        self.field = field
        self.ndim = field.ndim
        self.resolution = field.resolution
        self.origin = field.origin
        self.shape = field.shape
        self.risk_weight = float(risk_weight)
        self.robot_radius = float(robot_radius)
        self.risk = field.dilated_risk(robot_radius)
        self.valid = field.valid_mask(robot_radius, max_risk, allow_unknown)
        self.unknown = None if allow_unknown else field.dilated_unknown(robot_radius)
        self.turning_radius = float(turning_radius or 0.0)
        self.buffer = _segment_kernels.pack(
            self.risk, self.valid, self.origin, self.resolution, self.risk_weight, self.turning_radius
        )
        self.address = int(self.buffer.ctypes.data)
        self.endpoint_cells: tuple[int, ...] = ()  # the start's and goal's cells, set by plan()
        # z of the single layer when a 2-D grid is walked by the 3-D kernels
        self._z_plane = 0.5 * self.resolution

    @cached_property
    def valid_flat(self) -> list[bool]:
        """Validity per cell in C order as a list (built on first use: the grid planner needs none)."""
        return self.valid.reshape(-1).tolist()

    def eroded_valid_flat(self) -> list[bool]:
        """Validity of cells whose 3 x 3 (x 3) neighbourhood is valid, endpoint cells kept.

        A segment shorter than a cell that starts in such a cell stays in valid cells, so
        checking sampled poses against this mask is as safe as walking every cell. The start
        and goal cells stay valid (a segment from a pose to another in the same cell stays in
        that cell), so the erosion never turns a usable start or goal away.
        """
        # the minimum over the box, False beyond the map: no invalid cell (nor the outside) in the box
        invalid = box_max((~self.valid).view(np.uint8), (1,) * self.ndim, 1)
        flat = (invalid == 0).reshape(-1)
        for cell in self.endpoint_cells:
            flat[cell] = self.valid.reshape(-1)[cell]
        return flat.tolist()

    def _as3(self, positions: np.ndarray) -> np.ndarray:
        pts = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, self.ndim)
        if self.ndim == 3:
            return pts
        return np.column_stack([pts, np.full(len(pts), self._z_plane)])

    def evaluate(self, positions: np.ndarray) -> PathMeasures:
        """Exact length, risk integral, peak risk and first invalid segment of a polyline.

        Every cell each segment crosses is visited (no sampling), which is denser than
        any fixed step.
        """
        length, integral, peak, bad = _segment_kernels.evaluate_polyline(self.buffer, self._as3(positions))
        return PathMeasures(float(length), float(integral), float(peak), int(bad))

    def cost(self, positions: np.ndarray) -> float:
        """``length + w * integral`` of a polyline."""
        m = self.evaluate(positions)
        return m.length + self.risk_weight * m.integral

    def shortcut(self, positions: np.ndarray) -> np.ndarray:
        """Indices of the points kept by cost-non-increasing greedy string pulling."""
        return _segment_kernels.shortcut(self.buffer, self._as3(positions))

    def cell_index(self, position: tuple[float, ...]) -> int | None:
        """Flat index of the cell holding a position, None outside the map."""
        flat = 0
        for value, low, n in zip(position, self.origin, self.shape, strict=True):
            u = (value - low) / self.resolution
            if not (0.0 <= u < n) or not math.isfinite(u):
                return None
            flat = flat * n + int(u)
        return flat
