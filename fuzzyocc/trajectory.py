"""A sensor's trajectory over time (what a SLAM node publishes as a corrected ``nav_msgs/Path``), and a stored
scan re-posed on it.

- :class:`Trajectory`: stamps (integer Unix nanoseconds, strictly increasing), positions and unit
  quaternions ``[x, y, z, w]`` (ROS order) of one frame in the map, checked on construction with a
  ``ValueError`` naming the field and the index.
- :meth:`Trajectory.with_offset`: the sensor's trajectory from the robot's and a fixed mounting
  (a static TF ``base_link -> laser``): each pose ``T_map_sensor = T_map_base * T_base_sensor``.
- :meth:`Trajectory.poses_at`: the pose at each of a list of stamps, as tf2 looks it up: inside
  ``[first, last]`` only; at a sample's stamp that sample, bit for bit; between two samples the
  translation linearly and the rotation by slerp (:func:`fuzzyocc.tf.interpolate`, the rule
  ``TransformBuffer`` follows).
- :func:`repose`: a stored scan at another sensor pose, its beams and stamp kept. LaserScans only:
  a stored ``PointCloud`` keeps its points in the map frame and not its sensor's orientation, so it
  cannot be re-posed (docs/DESIGN.md, section 8.7).

Nothing here knows of ROS messages, storage or the web.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from fuzzyocc.scans import LaserScan, PointCloud
from fuzzyocc.tf import (
    UNIT_QUATERNION_TOLERANCE,
    Transform,
    interpolate,
    level_headings,
    nanoseconds_since_first,
    yaw_quaternion,
)

__all__ = ["PosesAt", "Trajectory", "laser_poses", "repose"]


def _stamps(name: str, value: object) -> np.ndarray:
    """Integer nanoseconds, 1-D, never negative (ROS time), as int64."""
    stamps = np.asarray(value)
    if stamps.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array of integer nanoseconds, got shape {stamps.shape}")
    if stamps.size and not np.issubdtype(stamps.dtype, np.integer):
        raise ValueError(f"{name} must be integer nanoseconds, got {stamps.dtype}")
    stamps = stamps.astype(np.int64)
    negative = np.flatnonzero(stamps < 0)
    if negative.size:
        i = int(negative[0])
        raise ValueError(f"{name}[{i}] is {stamps[i]}: ROS time is never negative")
    return stamps


def _rows(name: str, value: object, count: int, width: int) -> np.ndarray:
    """(count, width) finite float64, or a ``ValueError`` naming the first row that is not finite."""
    try:
        rows = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of numbers") from None
    if rows.shape != (count, width):
        raise ValueError(f"{name} must have shape ({count}, {width}) (one row per stamp), got {rows.shape}")
    bad = np.flatnonzero(~np.isfinite(rows).all(axis=1))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{name}[{i}] must be finite, got {rows[i].tolist()}")
    return rows


def _check_unit(name: str, quaternions: np.ndarray) -> None:
    """Each row a unit quaternion within ``UNIT_QUATERNION_TOLERANCE``, as a JSON scan's pose must be."""
    norms = np.linalg.norm(quaternions, axis=1)
    bad = np.flatnonzero(~(np.abs(norms - 1.0) <= UNIT_QUATERNION_TOLERANCE))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{name}[{i}] must be a unit quaternion [x, y, z, w] (ROS order), within "
                         f"{UNIT_QUATERNION_TOLERANCE:g}; its norm is {norms[i]:.6g}")


def _readonly(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


@dataclass(frozen=True)
class PosesAt:
    """The poses of a trajectory at some stamps (:meth:`Trajectory.poses_at`).

    Attributes
    ----------
    inside : (M,) ndarray of bool
        Whether each stamp lies in the trajectory's ``[first, last]``.
    positions : (M, 3) ndarray of float64
        The position at each stamp inside, NaN outside.
    quaternions : (M, 4) ndarray of float64
        The rotation ``[x, y, z, w]`` at each stamp inside, NaN outside.
    """

    inside: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Poses of one frame in the map over time, immutable and checked on construction.

    Parameters
    ----------
    stamps_ns : (N,) array_like of int
        Unix nanoseconds, >= 0, strictly increasing, N >= 1.
    positions : (N, 3) array_like of float
        Positions in the map frame, metres, finite.
    quaternions : (N, 4) array_like of float
        Rotations in the map frame, ``[x, y, z, w]`` (ROS order), finite, of norm 1 within
        ``UNIT_QUATERNION_TOLERANCE`` (1e-3, a JSON scan's pose's); kept as given (a sample is
        returned bit for bit), normalised where they are interpolated or composed.

    Raises
    ------
    ValueError
        Naming the field and the first bad index: ``"stamps_ns[3] (120) is not after
        stamps_ns[2] (120)"``, ``"positions[1] must be finite"``, ``"quaternions[0] must be a
        unit quaternion"``.
    """

    stamps_ns: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    _slerp: Slerp | None = field(init=False, repr=False, default=None)

    def __post_init__(self) -> None:
        stamps = _stamps("stamps_ns", self.stamps_ns)
        if stamps.size == 0:
            raise ValueError("stamps_ns must hold one stamp at least")
        back = np.flatnonzero(np.diff(stamps) <= 0)
        if back.size:
            i = int(back[0]) + 1
            raise ValueError(f"stamps_ns[{i}] ({stamps[i]}) is not after stamps_ns[{i - 1}] ({stamps[i - 1]}): "
                             "the stamps must strictly increase")
        positions = _rows("positions", self.positions, stamps.size, 3)
        quaternions = _rows("quaternions", self.quaternions, stamps.size, 4)
        _check_unit("quaternions", quaternions)
        set_ = object.__setattr__
        set_(self, "stamps_ns", _readonly(stamps))
        set_(self, "positions", _readonly(positions))
        set_(self, "quaternions", _readonly(quaternions))
        if stamps.size > 1:
            set_(self, "_slerp", Slerp(nanoseconds_since_first(stamps), Rotation.from_quat(quaternions)))

    def __len__(self) -> int:
        return int(self.stamps_ns.size)

    def __reduce__(self) -> tuple[type[Trajectory], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        # built again from its samples where it is unpickled (a process's answer): checked and read-only there too
        return Trajectory, (self.stamps_ns, self.positions, self.quaternions)

    def with_offset(self, position: object, quaternion_xyzw: object) -> Trajectory:
        """The trajectory of a frame fixed to this one: each pose composed with ``T_this_frame`` (``position``,
        metres, and ``quaternion_xyzw``, a unit quaternion), as a static TF ``base_link -> laser`` places the laser
        on a robot whose path this is."""
        offset_q = _rows("offset quaternion_xyzw", [quaternion_xyzw], 1, 4)
        _check_unit("offset quaternion_xyzw", offset_q)
        offset = Transform.of(_rows("offset position", [position], 1, 3)[0], offset_q[0])
        # one Transform holding every pose: scipy composes the N rotations at once, by Transform's own rule
        sensor = Transform(self.positions, Rotation.from_quat(self.quaternions)) * offset
        return Trajectory(self.stamps_ns, sensor.translation, sensor.rotation.as_quat())

    def poses_at(self, stamps_ns: object) -> PosesAt:
        """The pose at each stamp (integer Unix nanoseconds, any order), as tf2 looks one up.

        A stamp in ``[first, last]`` that is a sample's stamp gets that sample, bit for bit (no
        arithmetic); one between two samples gets the translation linearly and the rotation by
        slerp the shorter way round; one outside is flagged (``inside`` False), never extrapolated.
        """
        at = _stamps("stamps_ns", stamps_ns)
        stamps = self.stamps_ns
        inside = (at >= stamps[0]) & (at <= stamps[-1])
        positions = np.full((at.size, 3), np.nan)
        quaternions = np.full((at.size, 4), np.nan)
        index = np.minimum(np.searchsorted(stamps, at), stamps.size - 1)
        exact = inside & (stamps[index] == at)
        positions[exact] = self.positions[index[exact]]
        quaternions[exact] = self.quaternions[index[exact]]
        between = inside & ~exact
        if between.any():
            assert self._slerp is not None  # a stamp strictly between two samples: there are two
            translations, rotations = interpolate(stamps, self.positions, self._slerp, at[between])
            positions[between] = translations
            quaternions[between] = rotations.as_quat()
        return PosesAt(inside, positions, quaternions)


#: How far (in units in the last place) around the yaw read off a quaternion ``laser_poses`` looks for the yaw
#: ``yaw_quaternion`` writes it of, bit for bit.
_YAW_ULPS = 4


def _exact_yaws(quaternions: np.ndarray, yaws: np.ndarray, near: np.ndarray) -> np.ndarray:
    """For each quaternion that ``yaw_quaternion`` writes exactly of some yaw near ``yaw`` (within ``_YAW_ULPS``, or
    whole turns away, towards ``near``: a log's headings need not lie in [-pi, pi]), that yaw; else ``yaw``.

    A yaw read back from ``yaw_quaternion(theta)`` is wrapped, or off in its last bits, for 20 to 70 % of a shared
    CARMEN log's poses, and a map moves with one ulp of pose: so a trajectory published as yaw quaternions of the
    poses a map should have brings back those very poses. Neighbouring yaws can make the same quaternion: the one
    with the shortest decimal form wins (a log's ``1.52705``, not ``1.5270499999999998``), then the nearest.
    """
    out = yaws.copy()
    digits = np.full(yaws.size, np.iinfo(np.int64).max)
    level = (quaternions[:, 0] == 0.0) & (quaternions[:, 1] == 0.0)
    turns = np.round((near - yaws) / (2.0 * np.pi))
    for extra in (0.0, 1.0, -1.0):
        for step in sorted(range(-_YAW_ULPS, _YAW_ULPS + 1), key=abs):
            candidate = yaws + (turns + extra) * (2.0 * np.pi)
            for _ in range(abs(step)):
                candidate = np.nextafter(candidate, np.inf if step > 0 else -np.inf)
            half = 0.5 * candidate
            for i in np.flatnonzero(level & (np.sin(half) == quaternions[:, 2]) & (np.cos(half) == quaternions[:, 3])):
                length = len(repr(float(candidate[i])))
                if length < digits[i]:
                    out[i], digits[i] = candidate[i], length
    return out


def laser_poses(positions: object, quaternions_xyzw: object, near_yaws: object = None) -> np.ndarray:
    """The ``(x, y, theta)`` a LaserScan takes at each sensor pose (``positions`` (N, 3), ``quaternions_xyzw`` (N, 4)):
    ``theta`` the heading of the sensor's x axis (:func:`fuzzyocc.tf.level_heading`, the rule a LaserScan posted with
    a 3-D pose meets), ``z`` dropped; a quaternion ``yaw_quaternion`` writes exactly of some theta gives that theta
    bit for bit, the whole turns added that bring it nearest ``near_yaws`` (the scans' headings before, which
    may run past pi; None: within [-pi, pi]; ``_exact_yaws``). Raises ``NotLevel`` (naming the first index) for a
    pose tilted off level."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    quaternions = np.asarray(quaternions_xyzw, dtype=np.float64).reshape(-1, 4)
    yaws, _ = level_headings(quaternions)  # the turn is in the stored beams already
    near = yaws if near_yaws is None else np.asarray(near_yaws, dtype=np.float64).reshape(-1)
    return np.column_stack([positions[:, 0], positions[:, 1], _exact_yaws(quaternions, yaws, near)])


def repose(scan: LaserScan | PointCloud, position: object, quaternion_xyzw: object) -> LaserScan:
    """``scan`` taken from the sensor pose ``T_map_sensor`` (``position``, ``quaternion_xyzw``) instead: the same
    beams, stamp and settings, a new pose.

    A LaserScan's pose becomes ``(x, y, theta)``: ``theta`` the heading of the sensor's x axis
    (:func:`fuzzyocc.tf.level_heading`, the rule a LaserScan posted with a 3-D pose meets), ``z``
    dropped. Roll and pitch within ``LEVEL_TOLERANCE_RAD`` are dropped as they are when a scan is
    posted (the scan is fused flat); beyond it, :class:`fuzzyocc.tf.NotLevel`. A scanner upside
    down (z down) is fine: the stored beams already sweep the map's way, and are kept as stored
    (the record does not say whether the scanner was upside down, so it is taken to be mounted as
    it was). A quaternion that is exactly
    the one :func:`fuzzyocc.tf.yaw_quaternion` makes of the scan's own ``theta`` (its pose as ``GET
    /maps/{name}/trajectory`` gives it) keeps that ``theta`` bit for bit: a yaw read off a quaternion
    is wrapped to [-pi, pi] and may round, and a map moves with one ulp of pose.

    Raises
    ------
    NotImplementedError
        For a ``PointCloud``: its points are stored in the map frame with the sensor's origin only,
        so the rotation to undo is unknown (docs/DESIGN.md, section 8.7).
    ValueError
        A pose that is not finite, or that tilts the scanner off level (``NotLevel``).
    """
    if isinstance(scan, PointCloud):
        raise NotImplementedError("a stored PointCloud cannot be re-posed: it keeps its points in the map frame and "
                                  "its sensor's origin, not the orientation they were placed with")
    position_row = _rows("position", [position], 1, 3)
    quaternion = _rows("quaternion_xyzw", [quaternion_xyzw], 1, 4)
    if tuple(quaternion[0].tolist()) == yaw_quaternion(scan.pose[2]):
        return dataclasses.replace(scan, pose=(float(position_row[0, 0]), float(position_row[0, 1]), scan.pose[2]))
    x, y, theta = laser_poses(position_row, quaternion, [scan.pose[2]])[0]
    return dataclasses.replace(scan, pose=(float(x), float(y), float(theta)))
