"""Map geometry and sensor uncertainty: the two configs every map is built from.

Conventions (shared with ``planning``): a grid covers the axis-aligned box
``[origin, origin + size)`` in the ``map`` frame; cell ``(i, j[, k])`` runs along
x, y[, z] and its centre is ``origin + (index + 0.5) * resolution``. ``origin``
is the corner of cell 0, as in a Nav2 map YAML. Metres throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Largest |coordinate| of a map's box, metres: UTM northings (10,000 km) fit; beyond, float64 cell
#: centres lose sub-millimetre precision and the box stops meaning anything (an origin of 1e300
#: made every cell of a 10 m map the same point).
MAX_COORDINATE_M = 1e7
#: Largest sensor uncertainty accepted, metres (and metres per metre of range): beyond it every
#: beam is evidence of nothing.
MAX_SIGMA_M = 10.0
MAX_SIGMA_PER_M = 1.0

#: Default bound on the number of cells of one map (dense storage, about L + 2 bytes a cell for a
#: fuzzy map of L labels: 13 for the default engine).
DEFAULT_MAX_CELLS = 64_000_000


def _finite_tuple(name: str, values: object, dims: int | None = None) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a sequence of numbers, got {values!r}") from None
    if dims is not None and len(out) != dims:
        raise ValueError(f"{name} must have {dims} values, got {len(out)}")
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name} must be finite, got {out}")
    return out


def _cells(size: float, resolution: float) -> int:
    """Whole cells of ``resolution`` that cover ``size`` (a hair of tolerance for float noise)."""
    return max(1, math.ceil(size / resolution - 1e-9))


@dataclass(frozen=True)
class GridSpec:
    """A bounded 2-D or 3-D region cut into square (cubic) cells.

    Parameters
    ----------
    origin : sequence of 2 or 3 float
        Corner of cell 0 in the map frame, metres; the box must lie within
        ``MAX_COORDINATE_M`` of the frame's origin.
    size : sequence of 2 or 3 float
        Extent of the region along x, y[, z], metres; rounded up to whole cells.
    resolution : float
        Edge of a cell, metres.
    max_cells : int
        Refuse a grid with more cells than this (``ValueError`` naming ``size``).
    """

    origin: tuple[float, ...]
    size: tuple[float, ...]
    resolution: float
    max_cells: int = field(default=DEFAULT_MAX_CELLS, compare=False)

    def __post_init__(self) -> None:
        origin = _finite_tuple("origin", self.origin)
        if len(origin) not in (2, 3):
            raise ValueError(f"origin must have 2 or 3 values (a 2-D or 3-D map), got {len(origin)}")
        size = _finite_tuple("size", self.size, len(origin))
        res = float(self.resolution)
        if not math.isfinite(res) or res <= 0.0:
            raise ValueError(f"resolution must be a positive number of metres, got {self.resolution!r}")
        if any(s <= 0.0 for s in size):
            raise ValueError(f"size must be positive along every axis, got {size}")
        far = max(max(abs(o), abs(o + s)) for o, s in zip(origin, size))
        if far > MAX_COORDINATE_M:
            raise ValueError(f"origin {origin} and size {size} reach {far:.3g} m from the frame's origin, beyond "
                             f"{MAX_COORDINATE_M:.0e} m: use a local map frame")
        # counted in floats first: size / resolution can overflow an integer (1e300 / 1e-300)
        along = [s / res for s in size]
        if math.prod(along) > self.max_cells:
            raise ValueError(
                f"size {size} at resolution {res} m needs about {math.prod(along):.3g} cells, more than the limit "
                f"of {self.max_cells}; use a coarser resolution or a smaller region"
            )
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "resolution", res)
        cells = math.prod(self.shape)
        if cells > self.max_cells:
            raise ValueError(
                f"size {size} at resolution {res} m needs {cells} cells, more than the limit of "
                f"{self.max_cells}; use a coarser resolution or a smaller region"
            )

    @property
    def ndim(self) -> int:
        """2 or 3."""
        return len(self.origin)

    @property
    def shape(self) -> tuple[int, ...]:
        """Cells along x, y[, z]: ``ceil(size / resolution)`` (a hair of tolerance for float noise)."""
        return tuple(_cells(s, self.resolution) for s in self.size)

    @property
    def built_size(self) -> tuple[float, ...]:
        """The extent as built, ``shape * resolution``: a size that gives this very shape again.

        Written with 12 significant digits where that keeps the shape (16.0, not 16.000000000000004);
        a resolution of more digits (1/3) keeps the product as it is.
        """
        out = []
        for n in self.shape:
            exact = n * self.resolution
            short = float(f"{exact:.12g}")
            out.append(short if _cells(short, self.resolution) == n else exact)
        return tuple(out)

    @property
    def num_cells(self) -> int:
        """Total number of cells."""
        return math.prod(self.shape)

    @property
    def upper(self) -> tuple[float, ...]:
        """Far corner of the last cell (``origin + shape * resolution``)."""
        return tuple(o + n * self.resolution for o, n in zip(self.origin, self.shape))

    def cell_centers(self, axis: int) -> np.ndarray:
        """Coordinates of the cell centres along one axis, metres."""
        return self.origin[axis] + (np.arange(self.shape[axis]) + 0.5) * self.resolution


@dataclass(frozen=True)
class SensorModel:
    """Range uncertainty of a sensor and of the pose it is registered with.

    The effective standard deviation of a beam of range ``r`` is
    ``sqrt((range_sigma + range_sigma_per_m * r)**2 + registration_sigma**2)``,
    floored at half a cell by the map (the paper's "uncertainty on measurements
    and registration").

    Parameters
    ----------
    range_sigma : float
        Standard deviation of a range reading, metres (0.03 is a typical 2-D lidar); at most
        ``MAX_SIGMA_M``.
    registration_sigma : float
        Standard deviation of the pose estimate along the beam, metres; at most ``MAX_SIGMA_M``.
    range_sigma_per_m : float
        Growth of ``range_sigma`` with range, metres per metre (0 for a constant); at most
        ``MAX_SIGMA_PER_M``.
    """

    range_sigma: float = 0.03
    registration_sigma: float = 0.0
    range_sigma_per_m: float = 0.0

    def __post_init__(self) -> None:
        for name, high, unit in (("range_sigma", MAX_SIGMA_M, "m"), ("registration_sigma", MAX_SIGMA_M, "m"),
                                 ("range_sigma_per_m", MAX_SIGMA_PER_M, "m per m")):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0.0 or value > high:
                raise ValueError(f"{name} must be a number in [0, {high:g}] {unit}, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)

    def sigma(self, ranges: np.ndarray, extra_registration_sigma: float = 0.0) -> np.ndarray:
        """Effective sigma (metres) for beams of the given ranges, before the half-cell floor."""
        ranges = np.asarray(ranges, dtype=np.float64)
        range_part = self.range_sigma + self.range_sigma_per_m * ranges
        registration = math.hypot(self.registration_sigma, extra_registration_sigma)
        return np.sqrt(range_part * range_part + registration * registration)
