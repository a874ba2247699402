"""A quaternion's rotation of points, bit for bit as ``spatial.transform.Rotation`` computes it.

Maps are replayed from stored logs, so a cloud's points must land where they landed when the map was
built, to the last bit: this replaces ``Rotation.from_quat(q).apply(points)`` (SciPy is not among the
service's dependencies: a smaller image) with the same arithmetic in the same order. ``from_quat``
divides ``[x, y, z, w]`` by its norm ``sqrt(x x + y y + z z + w w)`` (summed in that order), the
matrix is its ``as_matrix`` formula, and ``apply`` is the very ``numpy.matmul`` call it makes
(tests/fuzzyocc/test_quaternion.py).
"""

from __future__ import annotations

import math

import numpy as np


def rotation_matrix(quaternion_xyzw: object) -> np.ndarray:
    """The (3, 3) matrix of the rotation ``[x, y, z, w]``, normalised here.

    Raises
    ------
    ValueError
        The quaternion is not 4 numbers, or has norm zero.
    """
    q = np.asarray(quaternion_xyzw, dtype=np.float64)
    if q.shape != (4,):
        raise ValueError(f"quaternion: expected 4 numbers [x, y, z, w], got shape {q.shape}")
    x, y, z, w = (float(v) for v in q)  # Python floats: IEEE doubles, one rounding per operation, no FMA
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm == 0.0:
        raise ValueError("quaternion: norm zero")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([
        [x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
        [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
        [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2],
    ])


def rotate_points(quaternion_xyzw: object, points: object) -> np.ndarray:
    """``points`` (N, 3) rotated by the quaternion ``[x, y, z, w]`` (normalised here): (N, 3) float64."""
    matrix = rotation_matrix(quaternion_xyzw)[np.newaxis]
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {pts.shape}")
    if len(pts) == 1:
        return np.matmul(matrix, pts[0])
    # the call Rotation.apply makes: another (pts @ matrix.T, sent to BLAS) may round differently
    return np.matmul(matrix, pts, axes=[(-2, -1), (-1, -2), (-1, -2)])[0]
