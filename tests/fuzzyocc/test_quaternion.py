"""fuzzyocc.quaternion against scipy's Rotation, which it replaces in the service: equal bit for bit.

Maps are replayed from stored logs, so a cloud's points must land exactly where scipy put them:
every matrix entry and rotated coordinate is compared as bits (the sign of a zero included), over
10,000 quaternions, unit and not, tiny and huge, with zeros, yaw-only as a ground robot's.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fuzzyocc.quaternion import rotate_points, rotation_matrix
from fuzzyocc.scans import PointCloud


def _same_bits(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype == np.float64 and a.shape == b.shape
    np.testing.assert_array_equal(a.view(np.int64), b.view(np.int64))


def _quaternions(count: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        q = rng.normal(size=4)
        kind = k % 6
        if kind == 1:
            q /= np.linalg.norm(q)  # as the callers pass it: normalised once more inside
        elif kind == 2:
            q *= 10.0 ** rng.uniform(-8, 8)
        elif kind == 3:
            q = np.round(q, 1)  # zeros and signed zeros among the components
        elif kind == 4:
            yaw = rng.uniform(-np.pi, np.pi)
            q = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]) * rng.uniform(0.5, 2.0)
        elif kind == 5:
            q[rng.integers(0, 4, size=2)] = -0.0
        if np.any(q):
            out.append(q)
    return out


def test_rotation_matrix_is_scipys() -> None:
    for q in _quaternions(10_000, 0):
        _same_bits(rotation_matrix(q), Rotation.from_quat(q).as_matrix())


def test_rotated_points_are_scipys() -> None:
    rng = np.random.default_rng(1)
    for k, q in enumerate(_quaternions(10_000, 1)):
        count = (1, 2, 3, int(rng.integers(4, 60)))[k % 4]
        points = rng.normal(size=(count, 3)) * 10.0 ** rng.uniform(-3, 3)
        _same_bits(rotate_points(q, points), Rotation.from_quat(q).apply(points))


def test_a_large_cloud_is_rotated_as_scipy_does() -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform(-30.0, 30.0, size=(200_000, 3))
    for q in _quaternions(6, 3):
        _same_bits(rotate_points(q, points), Rotation.from_quat(q).apply(points))
        _same_bits(rotate_points(q, points[::3]), Rotation.from_quat(q).apply(points[::3]))  # strided


def test_a_point_cloud_lands_where_it_did_with_scipy() -> None:
    rng = np.random.default_rng(4)
    points = rng.uniform(-5.0, 5.0, size=(500, 3))
    for q in _quaternions(50, 5):
        position = rng.uniform(-10.0, 10.0, size=3)
        cloud = PointCloud.from_sensor_frame(points, position, q, range_max=20.0)
        expected = Rotation.from_quat(q / np.linalg.norm(q)).apply(points) + position
        _same_bits(cloud.points, expected)


@pytest.mark.parametrize(
    ("quaternion", "points", "message"),
    [
        ([0.0, 0.0, 0.0, 0.0], np.ones((2, 3)), "norm zero"),
        ([0.0, 0.0, 1.0], np.ones((2, 3)), "4 numbers"),
        ([0.0, 0.0, 0.0, 1.0], np.ones((2, 2)), "shape"),
        ([0.0, 0.0, 0.0, 1.0], np.ones(3), "shape"),
    ],
)
def test_bad_input_is_refused(quaternion: list[float], points: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        rotate_points(quaternion, points)
