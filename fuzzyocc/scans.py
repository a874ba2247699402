"""Range scans as validated, immutable values, and their beams as rays.

Two kinds, both frozen dataclasses that check themselves on construction (``ValueError``
naming the field) and hold read-only float64 arrays:

- :class:`LaserScan`, a planar ``sensor_msgs/LaserScan`` with REP 117 semantics: beam ``i``
  points at ``theta + angle_min + i * angle_increment``; ``+inf`` or a range at or above
  ``range_max`` (older drivers send ``range_max`` or ``range_max + 1``) is a no-return that
  clears free space up to ``range_max`` and marks nothing occupied; ``-inf``, NaN (also JSON
  ``null``) and ranges below ``range_min`` are skipped.
- :class:`PointCloud`, beam end points in the map frame with the sensor origin; a point
  farther than ``range_max`` is cut at ``range_max`` and counts as a no-return (OctoMap's
  ``insertPointCloud(..., maxrange)``); a point at the origin is skipped.

Both carry the time they were taken, ``stamp_ns``: ROS time as integer Unix nanoseconds (exact, as
``builtin_interfaces/Time`` holds it), or None for a scan that has none. Fusion ignores it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from scipy.spatial.transform import Rotation

from fuzzyocc.config import _finite_tuple

#: A no-return cut at its neighbours' nearest hit stops this far in front of it (see
#: :meth:`Rays.cut_no_returns`): two cells at 0.05 m, clear of the surface band of that hit.
NO_RETURN_CUT_MARGIN_M = 0.1

#: Default cap on the beams of a LaserScan or the points of a PointCloud (per scan);
#: override per scan with ``max_rays=``.
DEFAULT_MAX_RAYS = 4_000_000


@dataclass(frozen=True)
class Rays:
    """The usable beams of one scan.

    Attributes
    ----------
    origin : (D,) ndarray of float64
        Sensor position, map frame, metres.
    directions : (N, D) ndarray of float64
        Unit beam directions.
    ranges : (N,) ndarray of float64
        Measured range of a hit, or ``range_max`` for a no-return, metres.
    hit : (N,) ndarray of bool
        True where the beam returned from a surface.
    skipped : int
        Beams of the scan that were dropped (REP 117 invalid readings, points at the origin).
    incidence : (N,) ndarray of float64, optional
        Sine of the angle at which each hit meets its surface (1 = head-on), estimated from
        the end points of the neighbouring beams; NaN where it cannot be (a no-return, an
        edge of the scan or of an object, a point cloud). None: not estimated.
    """

    origin: np.ndarray
    directions: np.ndarray
    ranges: np.ndarray
    hit: np.ndarray
    skipped: int
    incidence: np.ndarray | None = None

    def cut_no_returns(self, neighbours: int) -> Rays:
        """These rays with each no-return that has a hit among its ``neighbours`` beams on each side
        cut at the nearest of those hits, less :data:`NO_RETURN_CUT_MARGIN_M` (still a no-return:
        free space up to the cut, nothing beyond). Neighbours are in beam order (a LaserScan's)."""
        hit, n = self.hit, self.hit.size
        if neighbours <= 0 or n < 3 or hit.all() or not hit.any():
            return self
        hit_range = np.where(hit, self.ranges, np.inf)
        left, right = np.full(n, np.inf), np.full(n, np.inf)
        for k in range(1, min(neighbours, n - 1) + 1):
            left[k:] = np.minimum(left[k:], hit_range[:-k])
            right[:-k] = np.minimum(right[:-k], hit_range[k:])
        cut = ~hit & np.isfinite(left) & np.isfinite(right)
        if not cut.any():
            return self
        ranges = self.ranges.copy()
        nearest = np.minimum(left[cut], right[cut])
        ranges[cut] = np.minimum(ranges[cut], np.maximum(nearest - NO_RETURN_CUT_MARGIN_M, 0.0))
        return dataclasses.replace(self, ranges=ranges)

    def part(self, first: int, last: int, skipped: int) -> Rays:
        """Rays ``[first, last)`` of these, dropped beams counted as ``skipped``."""
        return Rays(origin=self.origin, directions=self.directions[first:last], ranges=self.ranges[first:last],
                    hit=self.hit[first:last], skipped=skipped,
                    incidence=None if self.incidence is None else self.incidence[first:last])

    @property
    def endpoints(self) -> np.ndarray:
        """(N, D) beam ends, map frame: the hit, or the ``range_max`` point of a no-return."""
        return self.origin + self.directions * self.ranges[:, None]


def _readonly(arr: np.ndarray) -> np.ndarray:
    arr.setflags(write=False)
    return arr


def _finite_scalar(name: str, value: object, *, minimum: float | None = None) -> float:
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise ValueError(f"{name} must be finite, got {out}")
    if minimum is not None and out < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {out}")
    return out


def _float_array(name: str, value: object) -> np.ndarray:
    try:
        return np.array(value, dtype=np.float64)  # a copy: the caller's array may change later
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of numbers") from None


_Scan = TypeVar("_Scan", "LaserScan", "PointCloud")


def _stamp_ns(value: object) -> int | None:
    """A scan's stamp checked: None, or an integer number of nanoseconds >= 0 (ROS time is never negative)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"stamp_ns must be an integer number of nanoseconds, got {value!r}")
    if value < 0:
        raise ValueError(f"stamp_ns must be >= 0 (Unix nanoseconds), got {value}")
    return int(value)


def _stamped(scan: _Scan, stamp_ns: int | None) -> _Scan:
    """``scan`` with another stamp: its arrays shared (read-only), nothing else checked again."""
    out = copy.copy(scan)
    object.__setattr__(out, "stamp_ns", _stamp_ns(stamp_ns))
    return out


def _check_count(name: str, count: int, max_rays: int) -> None:
    if count > max_rays:
        raise ValueError(f"{name} has {count} beams, more than the limit of {max_rays} per scan; split the scan")


#: Largest angle, radians, a LaserScan's beam may have (before it is wrapped).
MAX_ANGLE = 1e6


@dataclass(frozen=True, eq=False)
class LaserScan:
    """A planar scan (``sensor_msgs/LaserScan``) taken from a 2-D pose.

    Parameters
    ----------
    pose : (x, y, theta)
        Sensor pose in the map frame, metres and radians (yaw counter-clockwise, REP 103).
    angle_min : float
        Angle of beam 0 in the sensor frame, radians.
    angle_increment : float
        Angle between consecutive beams, radians (negative for a clockwise scan); non-zero
        unless the scan has a single range.
    ranges : (N,) array_like of float
        Readings, metres; may hold +inf, -inf and NaN (REP 117, see the module doc).
    range_min, range_max : float
        Valid reading interval, metres, ``0 <= range_min < range_max``.
    registration_sigma : float
        Extra pose uncertainty of this scan along its beams, metres, >= 0.
    max_rays : int
        Refuse a scan with more beams than this.
    stamp_ns : int, optional
        When the scan was taken: Unix nanoseconds, >= 0; None: unstamped.
    """

    pose: tuple[float, float, float]
    angle_min: float
    angle_increment: float
    ranges: np.ndarray
    range_min: float
    range_max: float
    registration_sigma: float = 0.0
    max_rays: int = field(default=DEFAULT_MAX_RAYS, repr=False)
    stamp_ns: int | None = None

    ndim = 2

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "pose", _finite_tuple("pose", self.pose, 3))
        set_(self, "angle_min", _finite_scalar("angle_min", self.angle_min))
        inc = _finite_scalar("angle_increment", self.angle_increment)
        set_(self, "angle_increment", inc)
        ranges = _float_array("ranges", self.ranges)
        if ranges.ndim != 1:
            raise ValueError(f"ranges must be a 1-D array, got shape {ranges.shape}")
        if inc == 0.0 and ranges.size > 1:  # one beam (a single-point rangefinder) has no increment
            raise ValueError("angle_increment must be non-zero for more than one range")
        _check_count("ranges", ranges.size, self.max_rays)
        # beyond this a beam's direction means nothing, and past float range it is NaN: a cast of NaN
        # directions wrote outside the map (a segfault at every restart)
        span = abs(self.pose[2]) + abs(self.angle_min) + max(ranges.size - 1, 0) * abs(inc)
        if not span <= MAX_ANGLE:
            raise ValueError(f"the beams' angles (pose theta + angle_min + i * angle_increment) must stay within "
                             f"{MAX_ANGLE:g} rad of 0, got up to {span:g}")
        set_(self, "ranges", _readonly(ranges))
        rmin = _finite_scalar("range_min", self.range_min, minimum=0.0)
        rmax = _finite_scalar("range_max", self.range_max, minimum=0.0)
        if rmax <= rmin:
            raise ValueError(f"range_max must be greater than range_min, got range_min={rmin}, range_max={rmax}")
        set_(self, "range_min", rmin)
        set_(self, "range_max", rmax)
        set_(self, "registration_sigma", _finite_scalar("registration_sigma", self.registration_sigma, minimum=0.0))
        set_(self, "stamp_ns", _stamp_ns(self.stamp_ns))

    def stamped(self, stamp_ns: int | None) -> LaserScan:
        """This scan taken at ``stamp_ns`` instead (its ranges shared, not copied)."""
        return _stamped(self, stamp_ns)

    @property
    def beam_count(self) -> int:
        """Readings in the scan, usable or not."""
        return int(self.ranges.size)

    def to_rays(self, incidence: bool = False, beams: slice | None = None) -> Rays:
        """The beams that carry information (hits and no-returns), in the map frame.

        ``incidence``: also estimate each hit's incidence on its surface (``Rays.incidence``).
        ``beams``: only the readings of this slice (step 1), the same rays as the whole scan's
        for those readings: a huge scan is cast part by part, in bounded memory.
        """
        first, last = self._bounds(beams)
        r = self.ranges[first:last]
        keep = r >= self.range_min  # False for NaN and -inf as well
        no_return = r >= self.range_max  # +inf and the legacy range_max / range_max + 1
        x, y, theta = self.pose
        beam = np.flatnonzero(keep)
        angles = theta + self.angle_min + (beam + first) * self.angle_increment
        directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        return Rays(
            origin=np.array([x, y]),
            directions=directions,
            ranges=np.where(no_return[beam], self.range_max, r[beam]),
            hit=~no_return[beam],
            skipped=int(r.size - beam.size),
            incidence=self._incidence_of(first, last)[beam] if incidence else None,
        )

    def _bounds(self, beams: slice | None) -> tuple[int, int]:
        n = self.ranges.size
        if beams is None:
            return 0, n
        first, last, step = beams.indices(n)
        if step != 1:
            raise ValueError(f"beams must be a slice of consecutive readings, got step {step}")
        return first, max(first, last)

    def incidence_of(self, beams: slice) -> np.ndarray:
        """``Rays.incidence`` of the rays ``to_rays(beams=beams)`` makes (the usable readings of ``beams``)."""
        first, last = self._bounds(beams)
        return self._incidence_of(first, last)[self.ranges[first:last] >= self.range_min]

    def _incidence_of(self, first: int, last: int) -> np.ndarray:
        """``_incidence`` of readings ``[first, last)``, from their neighbours (one more on each side)."""
        lo, hi = max(first - 1, 0), min(last + 1, self.ranges.size)
        r = self.ranges[lo:hi]
        hit = (r >= self.range_min) & (r < self.range_max)
        return _incidence(r, hit, self.angle_min + np.arange(lo, hi) * self.angle_increment)[first - lo:last - lo]

    def widen(self, beams: slice, kept: int) -> slice:
        """``beams`` (step 1) widened to hold ``kept`` usable readings more on each side, or up to the scan's ends:
        what :meth:`Rays.cut_no_returns` with that many neighbours reads of a part of the scan."""
        n = self.ranges.size
        first, last = self._bounds(beams)
        if kept <= 0:
            return slice(first, last)
        window = 8 * kept + 64
        while True:  # the nearest readings first: a scan of millions of beams is not searched whole per part
            lo = max(first - window, 0)
            before = np.flatnonzero(self.ranges[lo:first] >= self.range_min)
            if before.size >= kept or lo == 0:
                start = lo + int(before[-kept]) if before.size >= kept else 0
                break
            window *= 4
        window = 8 * kept + 64
        while True:
            hi = min(last + window, n)
            after = np.flatnonzero(self.ranges[last:hi] >= self.range_min)
            if after.size >= kept or hi == n:
                stop = last + int(after[kept - 1]) + 1 if after.size >= kept else n
                break
            window *= 4
        return slice(start, stop)

    def usable(self, beams: slice) -> int:
        """Readings in ``beams`` that ``to_rays`` keeps."""
        return int(np.count_nonzero(self.ranges[beams] >= self.range_min))


#: Neighbouring end points farther apart than this fraction of the range (or of 1 m, below
#: 1 m) lie on different surfaces: the incidence of the beam between them is not estimated.
INCIDENCE_MAX_GAP = 0.1


def _incidence(ranges: np.ndarray, hit: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Sine of each beam's incidence on its surface, from the chord between its neighbours' hits."""
    out = np.full(ranges.size, np.nan)
    if ranges.size < 3:
        return out
    with np.errstate(invalid="ignore"):
        r = np.where(hit, ranges, np.nan)
        px, py = r * np.cos(angles), r * np.sin(angles)  # sensor frame: the pose does not change angles
        tx, ty = px[2:] - px[:-2], py[2:] - py[:-2]
        chord = np.hypot(tx, ty)
        near = hit[2:] & hit[:-2] & hit[1:-1] & (chord > 0.0)
        near &= chord < INCIDENCE_MAX_GAP * np.maximum(ranges[1:-1], 1.0)
        c, s = np.cos(angles[1:-1]), np.sin(angles[1:-1])
        sine = np.abs(c * ty - s * tx) / np.where(chord > 0.0, chord, 1.0)
    out[1:-1] = np.where(near, np.minimum(sine, 1.0), np.nan)
    return out


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Beam end points of one sensor sweep, in the map frame, with the sensor origin.

    Parameters
    ----------
    points : (N, D) array_like of float
        End points, map frame, metres, finite; D = 2 or 3 (the map's dimension).
    origin : (D,) array_like of float
        Sensor position, map frame, metres.
    range_max : float
        Points farther than this from the origin are cut there and count as no-returns.
    registration_sigma : float
        Extra pose uncertainty of this sweep along its beams, metres, >= 0.
    max_rays : int
        Refuse a cloud with more points than this.
    stamp_ns : int, optional
        When the sweep was taken: Unix nanoseconds, >= 0; None: unstamped.
    sensor_points, sensor_pose : optional
        How the cloud was placed, when it was made from sensor-frame points (``from_sensor_frame``,
        ``from_planar_sensor_frame`` set them): those points, and the sensor pose ``(x, y, z, qx, qy, qz, qw)``
        or ``(x, y, theta)``. Kept so that the cloud can be stored as taken and placed again at another pose
        (a corrected trajectory) by the same arithmetic; not part of equality.
    """

    points: np.ndarray
    origin: tuple[float, ...]
    range_max: float
    registration_sigma: float = 0.0
    max_rays: int = field(default=DEFAULT_MAX_RAYS, repr=False)
    stamp_ns: int | None = None
    sensor_points: np.ndarray | None = field(default=None, repr=False, compare=False)
    sensor_pose: tuple[float, ...] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        points = _float_array("points", self.points)
        if points.ndim != 2 or points.shape[1] not in (2, 3):
            raise ValueError(f"points must have shape (N, 2) or (N, 3), got {points.shape}")
        _check_count("points", points.shape[0], self.max_rays)
        if not np.all(np.isfinite(points)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(points), axis=1))[0])
            raise ValueError(f"points must be finite; row {bad} is {points[bad].tolist()}")
        set_(self, "points", _readonly(points))
        set_(self, "origin", _finite_tuple("origin", self.origin, points.shape[1]))
        rmax = _finite_scalar("range_max", self.range_max)
        if rmax <= 0.0:
            raise ValueError(f"range_max must be positive, got {rmax}")
        set_(self, "range_max", rmax)
        set_(self, "registration_sigma", _finite_scalar("registration_sigma", self.registration_sigma, minimum=0.0))
        set_(self, "stamp_ns", _stamp_ns(self.stamp_ns))
        if (self.sensor_points is None) != (self.sensor_pose is None):
            raise ValueError("sensor_points and sensor_pose go together")
        if self.sensor_points is not None:
            set_(self, "sensor_points", _readonly(_float_array("sensor_points", self.sensor_points)))
            set_(self, "sensor_pose", tuple(float(v) for v in self.sensor_pose))  # type: ignore[union-attr]

    def stamped(self, stamp_ns: int | None) -> PointCloud:
        """This cloud taken at ``stamp_ns`` instead (its points shared, not copied)."""
        return _stamped(self, stamp_ns)

    @property
    def ndim(self) -> int:
        """2 or 3."""
        return self.points.shape[1]

    @classmethod
    def from_sensor_frame(
        cls,
        points_sensor: object,
        position: object,
        quaternion_xyzw: object,
        range_max: float,
        registration_sigma: float = 0.0,
        stamp_ns: int | None = None,
        max_rays: int = DEFAULT_MAX_RAYS,
    ) -> PointCloud:
        """A cloud from sensor-frame points and the sensor pose ``T_map_sensor``.

        Parameters
        ----------
        points_sensor : (N, 3) array_like of float
            End points in the sensor frame, metres.
        position : (3,) array_like of float
            Sensor position in the map frame, metres.
        quaternion_xyzw : (4,) array_like of float
            Sensor orientation in the map frame, ``[x, y, z, w]``; normalised here.
        range_max, registration_sigma, stamp_ns, max_rays
            As in the constructor.
        """
        pts = _float_array("points", points_sensor)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3) in the sensor frame, got {pts.shape}")
        position_map = np.array(_finite_tuple("position", position, 3))
        quat = np.array(_finite_tuple("quaternion_xyzw", quaternion_xyzw, 4))
        if np.linalg.norm(quat) < 1e-9:
            raise ValueError("quaternion_xyzw must have a non-zero norm")
        # normalised here and again by from_quat, as when stored maps were built: one division fewer moves points an ulp
        points_map = Rotation.from_quat(quat / np.linalg.norm(quat)).apply(pts) + position_map if pts.size else pts
        return cls(points=points_map, origin=tuple(position_map), range_max=range_max,
                   registration_sigma=registration_sigma, max_rays=max_rays, stamp_ns=stamp_ns, sensor_points=pts,
                   sensor_pose=(*position_map.tolist(), *quat.tolist()))

    @classmethod
    def from_planar_sensor_frame(
        cls,
        points_sensor: object,
        pose: tuple[float, float, float],
        range_max: float,
        registration_sigma: float = 0.0,
        stamp_ns: int | None = None,
        max_rays: int = DEFAULT_MAX_RAYS,
    ) -> PointCloud:
        """A 2-D cloud from ``(N, 2)`` sensor-frame points and a planar sensor pose ``(x, y, theta)`` (REP 103)."""
        pts = _float_array("points", points_sensor)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"points must have shape (N, 2) in the sensor frame, got {pts.shape}")
        x, y, theta = _finite_tuple("pose", pose, 3)
        c, s = math.cos(theta), math.sin(theta)
        points_map = pts @ np.array([[c, -s], [s, c]]).T + np.array([x, y])
        return cls(points=points_map, origin=(x, y), range_max=range_max, registration_sigma=registration_sigma,
                   max_rays=max_rays, stamp_ns=stamp_ns, sensor_points=pts, sensor_pose=(x, y, theta))

    @property
    def beam_count(self) -> int:
        """Points in the cloud."""
        return int(self.points.shape[0])

    def to_rays(self, beams: slice | None = None) -> Rays:
        """The beams from the origin to each point (cut at ``range_max``), in the map frame.

        ``beams``: only the points of this slice (a huge cloud is cast part by part).
        """
        origin = np.asarray(self.origin)
        points = self.points if beams is None else self.points[beams]
        offsets = points - origin
        dist = np.linalg.norm(offsets, axis=1)
        beam = np.flatnonzero(dist > 0.0)
        dist = dist[beam]
        return Rays(
            origin=origin,
            directions=offsets[beam] / dist[:, None],
            ranges=np.minimum(dist, self.range_max),
            hit=dist <= self.range_max,
            skipped=int(points.shape[0] - beam.size),
        )
