"""Request bodies to checked scans: a JSON ``ScanBatch``, or one binary scan (``.npy`` or raw float32).

Everything a body needs is checked here, before anything is stored or applied: the batch's size,
a ``.npy`` header or a raw body's length before its data is read; each scan is then built by
``app.scans.scan`` (the limits and the map's dimension). Errors name the field (``scans[2].pose``)
and say what to fix.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence

import numpy as np
from pydantic import ValidationError

from app.errors import Invalid, TooLarge
from app.formats.mediatypes import NPY, OCTET_STREAM
from app.scans.scan import Limits, Scan, check_rays, laser_scan, point_cloud
from app.schemas import LaserScanIn, PointCloudIn, Pose2D, Pose3D, ScanBatch

#: Content types of the binary upload (one scan per request, pose in the query).
BINARY_TYPES = (OCTET_STREAM, NPY)
_NPY_MAGIC = b"\x93NUMPY"


def _check_batch_size(count: int, limits: Limits) -> None:
    if count > limits.max_scans:
        raise TooLarge(
            f"the batch has {count} scans, more than the limit of {limits.max_scans} "
            "(FUZZYRISK_MAX_SCANS_PER_BATCH): send several batches"
        )


def from_json(batch: ScanBatch, dims: int, limits: Limits) -> list[Scan]:
    """The scans of a JSON batch, validated for a map of ``dims`` dimensions."""
    _check_batch_size(len(batch.scans), limits)
    scans: list[Scan] = []
    for i, scan in enumerate(batch.scans):
        name = f"scans[{i}]"
        stamp_ns = None if scan.header is None else scan.header.stamp_ns()
        if isinstance(scan, LaserScanIn):
            # numpy reads null as NaN and the strings "inf", "-inf", "nan" (and Infinity) as floats
            ranges = np.array(scan.ranges, dtype=np.float64)
            scans.append(laser_scan(
                name, scan.pose, angle_min=scan.angle_min, angle_increment=scan.angle_increment, ranges=ranges,
                range_min=scan.range_min, range_max=scan.range_max, registration_sigma=scan.registration_sigma,
                dims=dims, limits=limits, stamp_ns=stamp_ns,
            ))
        else:
            assert isinstance(scan, PointCloudIn)
            if len({len(row) for row in scan.points}) > 1:
                raise Invalid(f"{name}.points rows must all have {dims} coordinates")
            points = np.array(scan.points, dtype=np.float64)
            scans.append(point_cloud(
                name, scan.pose, points, range_max=scan.range_max, registration_sigma=scan.registration_sigma,
                dims=dims, limits=limits, stamp_ns=stamp_ns,
            ))
    return scans


# ---------------------------------------------------------------- binary upload


def _npy_header(body: bytes) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """(shape, fortran_order, dtype, data offset) of a ``.npy`` body, read without loading the data."""
    stream = io.BytesIO(body)
    try:
        major, minor = np.lib.format.read_magic(stream)
        if (major, minor) == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream)
        elif (major, minor) == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream)
        else:
            raise Invalid(f"body: .npy format version {major}.{minor} is not read here: save with numpy.save "
                          "(version 1.0 or 2.0)")
    except Invalid:
        raise
    except Exception as exc:
        # a hostile header reaches ast/tokenize inside numpy, which raise ValueError, SyntaxError,
        # tokenize.TokenError, RecursionError...: every one of them means "not a .npy we can read"
        raise Invalid(f"body: not a readable .npy header ({type(exc).__name__}: {exc}); "
                      "save the array with numpy.save") from None
    return tuple(shape), bool(fortran), dtype, stream.tell()


def _load_npy(body: bytes, limits: Limits) -> np.ndarray:
    """The float64 array of a ``.npy`` body; the header is checked before any data is touched.

    A header can claim any shape: the beam count is checked against the limit (413) and the
    byte count against the bytes actually sent (422) before an array is made, so a lying
    header costs nothing.
    """
    shape, fortran, dtype, offset = _npy_header(body)
    if dtype.kind != "f" or dtype.itemsize not in (4, 8):
        raise Invalid(f"body: the .npy array must be float32 or float64, got {dtype}")
    if dtype.byteorder not in ("<", "="):
        raise Invalid(f"body: the .npy array is big-endian ({dtype.str}): send little-endian float32 or float64")
    if len(shape) not in (1, 2):
        raise Invalid(f"body: the .npy array must be (N,) ranges or (N, D) points, got shape {shape}")
    if any(n < 0 for n in shape):
        raise Invalid(f"body: the .npy header claims a negative dimension in shape {shape}")
    check_rays("body", shape[0], limits)
    need = math.prod(shape) * dtype.itemsize  # Python ints: a claim of 10**12 beams cannot overflow
    have = len(body) - offset
    if need != have:
        raise Invalid(
            f"body: the .npy header says shape {shape} of {dtype} ({need} bytes) but {have} bytes follow the "
            "header: the file is truncated or has trailing bytes"
        )
    array = np.frombuffer(body, dtype=dtype, count=math.prod(shape), offset=offset)
    return array.reshape(shape, order="F" if fortran else "C").astype(np.float64)


def _load_body(body: bytes, limits: Limits) -> tuple[np.ndarray, bool]:
    """(float64 array, came from .npy): a ``.npy`` file, or raw little-endian float32 values (1-D)."""
    if body.startswith(_NPY_MAGIC):
        return _load_npy(body, limits), True
    if not body:
        raise Invalid("body is empty: send a .npy array or raw little-endian float32 values")
    if len(body) % 4:
        raise Invalid(f"body: {len(body)} bytes is not a whole number of float32 values (4 bytes each)")
    return np.frombuffer(body, dtype="<f4").astype(np.float64), False


def _raw_points(body: bytes, point_step: float | None, limits: Limits) -> np.ndarray:
    """(N, 3) float32 points of a raw body, viewed in place: ``point_step`` bytes a point, x, y, z little-endian
    float32 first.

    Raw bytes do not say their layout, and guessing 12 bytes a point read a 16-byte-stride
    PointCloud2 (x, y, z, intensity) as 400 garbage points instead of 300: the stride
    is stated or the body refused.
    """
    if not body:
        raise Invalid("body is empty: send the points' bytes")
    if point_step is None:
        raise Invalid("body: raw float32 points need their layout: point_step=12 for packed x y z (bytes per point, "
                      "x, y, z little-endian float32 at its start; 16 for x y z + one float32, e.g. a PointCloud2's "
                      "intensity); or send a .npy of shape (N, 3), or the PointCloud2 itself as "
                      "application/vnd.ros2.sensor_msgs.msg.PointCloud2+cdr")
    step = int(point_step)
    check_rays("body", len(body) // step, limits)
    if len(body) % step:
        raise Invalid(f"body: {len(body)} bytes is not a whole number of points of point_step {step} bytes")
    # a strided view of the body: fuzzyocc converts the points to float64 once, as it places them
    return np.ndarray((len(body) // step, 3), dtype="<f4", buffer=body, strides=(step, 4))


def _need(params: Mapping[str, float | None], names: Sequence[str], what: str) -> list[float]:
    missing = [n for n in names if params.get(n) is None]
    if missing:
        raise Invalid(f"{what} needs the query parameters {', '.join(missing)}")
    return [float(params[n]) for n in names]  # type: ignore[arg-type]


def from_binary(body: bytes, params: Mapping[str, float | None], dims: int, limits: Limits) -> list[Scan]:
    """The one scan of a binary upload (pose and scan parameters in ``params``, from the query).

    3-D map: points (N, 3) in the sensor frame (``.npy``, or raw points of ``point_step`` bytes, each
    starting with float32 x, y, z), pose ``x, y, z`` and quaternion ``qx, qy, qz, qw`` (default
    identity), ``range_max``.
    2-D map: raw float32 ranges (or a 1-D ``.npy``) of a LaserScan with ``x, y, theta, angle_min,
    angle_increment, range_min, range_max``; or a ``.npy`` of (N, 2) sensor-frame points with
    ``x, y, theta, range_max``.
    """
    registration_sigma = params.get("registration_sigma") or 0.0
    point_step = params.get("point_step")
    if dims == 3 and not body.startswith(_NPY_MAGIC):
        array = _raw_points(body, point_step, limits)
    elif point_step is not None:
        raise Invalid("query: point_step describes raw float32 points on a 3-D map; drop it here")
    else:
        array, _ = _load_body(body, limits)
    if dims == 3:
        x, y, z, range_max = _need(params, ("x", "y", "z", "range_max"), "a point cloud on a 3-D map")
        given = [params.get(k) for k in ("qx", "qy", "qz", "qw")]
        quaternion = [d if q is None else q for q, d in zip(given, (0.0, 0.0, 0.0, 1.0))]  # identity by default
        try:
            pose: Pose2D | Pose3D = Pose3D(position=[x, y, z], orientation=quaternion)
        except ValidationError as exc:
            raise Invalid(f"query: {exc.errors()[0]['msg']}") from None
        return [point_cloud("body", pose, array, range_max=range_max, registration_sigma=registration_sigma,
                            dims=3, limits=limits)]
    x, y, theta = _need(params, ("x", "y", "theta"), "a scan on a 2-D map")
    pose = Pose2D(x=x, y=y, theta=theta)
    if array.ndim == 2:
        (range_max,) = _need(params, ("range_max",), "a 2-D point cloud")
        return [point_cloud("body", pose, array, range_max=range_max, registration_sigma=registration_sigma,
                            dims=2, limits=limits)]
    if array.ndim != 1:
        raise Invalid(f"body: the .npy array must be (N,) ranges or (N, 2) points on a 2-D map, got {array.shape}")
    angle_min, angle_increment, range_min, range_max = _need(
        params, ("angle_min", "angle_increment", "range_min", "range_max"), "a LaserScan"
    )
    return [laser_scan("body", pose, angle_min=angle_min, angle_increment=angle_increment, ranges=array,
                       range_min=range_min, range_max=range_max, registration_sigma=registration_sigma,
                       dims=2, limits=limits)]
