"""World coordinates <-> integer cell keys, over ``(N, D)`` arrays, masked instead of wrapped.

A key is the integer index ``(i, j[, k])`` of a cell along x, y[, z]; the flat id of a cell is
its position in the C-ordered array of ``spec.shape`` (``np.ravel_multi_index``). A point
belongs to the cell whose half-open box ``[origin + key * res, origin + (key + 1) * res)``
contains it, so a point on the far face of the map (``spec.upper``) is outside.
"""

from __future__ import annotations

import numpy as np

from fuzzyocc.config import GridSpec


def _points_array(spec: GridSpec, points: object, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != spec.ndim:
        raise ValueError(f"{name} must have shape (N, {spec.ndim}) for a {spec.ndim}-D map, got {arr.shape}")
    return arr


def coords_to_keys(spec: GridSpec, points: object) -> tuple[np.ndarray, np.ndarray]:
    """Cell keys of world points, with a mask of the points that lie inside the map.

    Parameters
    ----------
    spec : GridSpec
        The grid.
    points : (N, D) array_like of float
        World coordinates, metres.

    Returns
    -------
    keys : (N, D) ndarray of int64
        Cell index along each axis. Rows where ``valid`` is False are clipped to the nearest
        cell (never wrapped) so that indexing with them cannot fail; mask them out.
    valid : (N,) ndarray of bool
        True where the point is finite and inside ``[origin, upper)``.

    Raises
    ------
    ValueError
        If ``points`` is not of shape (N, D).

    Examples
    --------
    >>> spec = GridSpec(origin=(0.0, 0.0), size=(1.0, 1.0), resolution=0.5)
    >>> keys, valid = coords_to_keys(spec, [[0.2, 0.7], [1.0, 0.1]])
    >>> keys.tolist(), valid.tolist()
    ([[0, 1], [1, 0]], [True, False])
    """
    pts = _points_array(spec, points, "points")
    origin = np.asarray(spec.origin)
    shape = np.asarray(spec.shape)
    with np.errstate(invalid="ignore"):
        scaled = np.floor((pts - origin) / spec.resolution)
        valid = np.all((scaled >= 0) & (scaled < shape), axis=1)  # False for NaN and inf too
    scaled = np.nan_to_num(scaled, nan=0.0, posinf=0.0, neginf=0.0)
    keys = np.clip(scaled, 0, shape - 1).astype(np.int64)
    return keys, valid


def keys_to_coords(spec: GridSpec, keys: object) -> np.ndarray:
    """Centres of the cells with the given keys, ``origin + (key + 0.5) * resolution``.

    Parameters
    ----------
    spec : GridSpec
        The grid.
    keys : (N, D) array_like of int
        Cell keys (not checked against the shape: a key outside gives a centre outside).

    Returns
    -------
    (N, D) ndarray of float64
    """
    k = np.asarray(keys)
    if k.ndim != 2 or k.shape[1] != spec.ndim:
        raise ValueError(f"keys must have shape (N, {spec.ndim}), got {k.shape}")
    return np.asarray(spec.origin) + (k + 0.5) * spec.resolution


def keys_to_flat(spec: GridSpec, keys: np.ndarray) -> np.ndarray:
    """Flat cell ids (C order over ``spec.shape``) of in-range keys; raises ValueError if one is out."""
    return np.ravel_multi_index(tuple(np.asarray(keys).T), spec.shape).astype(np.int64)


def flat_to_keys(spec: GridSpec, flat: np.ndarray) -> np.ndarray:
    """Keys ``(N, D)`` of flat cell ids; the inverse of :func:`keys_to_flat`."""
    return np.stack(np.unravel_index(np.asarray(flat), spec.shape), axis=1).astype(np.int64)
