"""The checked scan: a fuzzyocc ``LaserScan`` or ``PointCloud`` built for one map, within the limits.

pydantic checks shapes and finiteness, this module the limits and the map's dimension, and
constructing ``LaserScan`` / ``PointCloud`` runs fuzzyocc's own checks. Every way a scan comes in
(JSON and binary bodies, ``app.scans.bodies``; ROS messages, ``app.ros.messages_in``) ends here.
Errors name the field (``scans[2].pose``) and say what to fix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.errors import Invalid, TooLarge
from app.schemas import Pose2D, Pose3D
from fuzzyocc import LaserScan, PointCloud

Scan = LaserScan | PointCloud


@dataclass(frozen=True)
class Limits:
    """What a batch may hold: scans per batch (``FUZZYRISK_MAX_SCANS_PER_BATCH``), beams per scan
    (``FUZZYRISK_MAX_RAYS_PER_SCAN``)."""

    max_scans: int
    max_rays: int


def check_rays(name: str, count: int, limits: Limits) -> None:
    """413 when ``name`` has more than ``limits.max_rays`` beams (checked before its beams are read)."""
    if count > limits.max_rays:
        raise TooLarge(
            f"{name} has {count} beams, more than the limit of {limits.max_rays} per scan "
            "(FUZZYRISK_MAX_RAYS_PER_SCAN): split it into several scans"
        )


def finite_rows(points: np.ndarray) -> np.ndarray:
    """The (N, D) rows of an (..., D) array whose D values are all finite, in their order.

    Organised clouds (a ROS PointCloud2 with ``is_dense`` false) mark a no-return with NaN: those rows go.
    Axis by axis, on the view as it comes (a PointCloud2's ``data`` with its strides): ``np.isfinite(p).all(-1)``
    and ``p[mask]`` over an OS-1-128 cloud's strided view took 6-7 ms, these 1 ms. Nothing is copied when every
    row is finite and the rows reshape without a copy: a lidar's cloud is copied once, as fuzzyocc places it.
    """
    finite = np.isfinite(points[..., 0])
    for axis in range(1, points.shape[-1]):
        finite &= np.isfinite(points[..., axis])
    if finite.all():
        return points.reshape(-1, points.shape[-1])
    rows = np.empty((int(np.count_nonzero(finite)), points.shape[-1]), dtype=points.dtype)
    for axis in range(points.shape[-1]):
        rows[:, axis] = points[..., axis][finite]
    return rows


def _value_error(name: str, exc: ValueError) -> Invalid:
    return Invalid(f"{name}: {exc}")


def laser_scan(
    name: str, pose: Pose2D, *, angle_min: float, angle_increment: float, ranges: np.ndarray, range_min: float,
    range_max: float, registration_sigma: float, dims: int, limits: Limits, stamp_ns: int | None = None,
) -> LaserScan:
    """A validated ``LaserScan`` for a map of ``dims`` dimensions, taken at ``stamp_ns`` (None: unstamped)."""
    if dims != 2:
        raise Invalid(f"{name} is a LaserScan (planar) but the map is 3-D: send a point cloud with a 3-D pose")
    check_rays(f"{name}.ranges", ranges.size, limits)
    try:
        return LaserScan(
            pose=(pose.x, pose.y, pose.theta), angle_min=angle_min, angle_increment=angle_increment,
            ranges=ranges, range_min=range_min, range_max=range_max, registration_sigma=registration_sigma,
            max_rays=limits.max_rays, stamp_ns=stamp_ns,
        )
    except ValueError as exc:
        raise _value_error(name, exc) from None


def point_cloud(
    name: str, pose: Pose2D | Pose3D, points_sensor: np.ndarray, *, range_max: float, registration_sigma: float,
    dims: int, limits: Limits, stamp_ns: int | None = None,
) -> PointCloud:
    """A validated map-frame ``PointCloud`` from sensor-frame points and the sensor pose, taken at ``stamp_ns``."""
    # the pose first: a 3-D cloud sent to a 2-D map is a wrong map, not wrong points
    if dims == 3 and not isinstance(pose, Pose3D):
        raise Invalid(f"{name}.pose must be {{position: [x, y, z], orientation: [qx, qy, qz, qw]}} on a 3-D map")
    if dims == 2 and not isinstance(pose, Pose2D):
        raise Invalid(f"{name}.pose must be {{x, y, theta}} on a 2-D map (a 3-D pose and (N, 3) points need a "
                      "map created with dimensions 3)")
    if points_sensor.ndim != 2 or points_sensor.shape[1] != dims:
        raise Invalid(f"{name}.points must have shape (N, {dims}) for this {dims}-D map, got {points_sensor.shape}")
    check_rays(f"{name}.points", points_sensor.shape[0], limits)
    points_sensor = finite_rows(points_sensor)
    try:
        if isinstance(pose, Pose3D):
            return PointCloud.from_sensor_frame(
                points_sensor, pose.position, pose.orientation, range_max, registration_sigma, stamp_ns,
                max_rays=limits.max_rays,
            )
        return PointCloud.from_planar_sensor_frame(
            points_sensor, (pose.x, pose.y, pose.theta), range_max, registration_sigma, stamp_ns,
            max_rays=limits.max_rays,
        )
    except ValueError as exc:
        raise _value_error(name, exc) from None

