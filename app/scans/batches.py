"""Scan batches: from request bodies (JSON or binary) to validated fuzzyocc scans, and to bytes on disk.

Everything a batch needs is checked here, before anything is stored or applied:
pydantic checks shapes and finiteness, this module the limits and the map's
dimension, and constructing ``LaserScan`` / ``PointCloud`` runs fuzzyocc's own checks.
Errors name the field (``scans[2].pose``) and say what to fix.
"""

from __future__ import annotations

import io
import json
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from pydantic import ValidationError

from app.errors import Invalid, TooLarge
from app.formats.mediatypes import NPY, OCTET_STREAM
from app.schemas import LaserScanIn, PointCloudIn, Pose2D, Pose3D, ScanBatch
from fuzzyocc import LaserScan, PointCloud
from fuzzyocc.maps import scan_parts

Scan = LaserScan | PointCloud

#: Content types of the binary upload (one scan per request, pose in the query).
BINARY_TYPES = (OCTET_STREAM, NPY)
_NPY_MAGIC = b"\x93NUMPY"
#: The scans/last view draws at most this many beams.
MAX_VIEW_BEAMS = 4096


@dataclass(frozen=True)
class Limits:
    max_scans: int
    max_rays: int


def _check_rays(name: str, count: int, limits: Limits) -> None:
    if count > limits.max_rays:
        raise TooLarge(
            f"{name} has {count} beams, more than the limit of {limits.max_rays} per scan "
            "(FUZZYRISK_MAX_RAYS_PER_SCAN): split it into several scans"
        )


def _planar_to_map(points_sensor: np.ndarray, pose: Pose2D) -> np.ndarray:
    """(N, 2) sensor-frame points -> map frame under a planar pose."""
    c, s = math.cos(pose.theta), math.sin(pose.theta)
    rotation = np.array([[c, -s], [s, c]])
    return points_sensor @ rotation.T + np.array([pose.x, pose.y])


def _finite_rows(points: np.ndarray) -> np.ndarray:
    # organised clouds (ROS PointCloud2 with is_dense false) mark a no-return with NaN: drop those rows
    return points[np.isfinite(points).all(axis=1)]


def _value_error(name: str, exc: ValueError) -> Invalid:
    return Invalid(f"{name}: {exc}")


def laser_scan(
    name: str, pose: Pose2D, *, angle_min: float, angle_increment: float, ranges: np.ndarray, range_min: float,
    range_max: float, registration_sigma: float, dims: int, limits: Limits,
) -> LaserScan:
    """A validated ``LaserScan`` for a map of ``dims`` dimensions."""
    if dims != 2:
        raise Invalid(f"{name} is a LaserScan (planar) but the map is 3-D: send a point cloud with a 3-D pose")
    _check_rays(f"{name}.ranges", ranges.size, limits)
    try:
        return LaserScan(
            pose=(pose.x, pose.y, pose.theta), angle_min=angle_min, angle_increment=angle_increment,
            ranges=ranges, range_min=range_min, range_max=range_max, registration_sigma=registration_sigma,
            max_rays=limits.max_rays,
        )
    except ValueError as exc:
        raise _value_error(name, exc) from None


def point_cloud(
    name: str, pose: Pose2D | Pose3D, points_sensor: np.ndarray, *, range_max: float, registration_sigma: float,
    dims: int, limits: Limits,
) -> PointCloud:
    """A validated map-frame ``PointCloud`` from sensor-frame points and the sensor pose."""
    # the pose first: a 3-D cloud sent to a 2-D map is a wrong map, not wrong points
    if dims == 3 and not isinstance(pose, Pose3D):
        raise Invalid(f"{name}.pose must be {{position: [x, y, z], orientation: [qx, qy, qz, qw]}} on a 3-D map")
    if dims == 2 and not isinstance(pose, Pose2D):
        raise Invalid(f"{name}.pose must be {{x, y, theta}} on a 2-D map (a 3-D pose and (N, 3) points need a "
                      "map created with dimensions 3)")
    if points_sensor.ndim != 2 or points_sensor.shape[1] != dims:
        raise Invalid(f"{name}.points must have shape (N, {dims}) for this {dims}-D map, got {points_sensor.shape}")
    _check_rays(f"{name}.points", points_sensor.shape[0], limits)
    points_sensor = _finite_rows(points_sensor)
    try:
        if isinstance(pose, Pose3D):
            return PointCloud.from_sensor_frame(
                points_sensor, pose.position, pose.orientation, range_max, registration_sigma
            )
        return PointCloud(
            points=_planar_to_map(points_sensor, pose), origin=(pose.x, pose.y), range_max=range_max,
            registration_sigma=registration_sigma, max_rays=limits.max_rays,
        )
    except ValueError as exc:
        raise _value_error(name, exc) from None


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
        if isinstance(scan, LaserScanIn):
            # numpy reads null as NaN and the strings "inf", "-inf", "nan" (and Infinity) as floats
            ranges = np.array(scan.ranges, dtype=np.float64)
            scans.append(laser_scan(
                name, scan.pose, angle_min=scan.angle_min, angle_increment=scan.angle_increment, ranges=ranges,
                range_min=scan.range_min, range_max=scan.range_max, registration_sigma=scan.registration_sigma,
                dims=dims, limits=limits,
            ))
        else:
            assert isinstance(scan, PointCloudIn)
            if len({len(row) for row in scan.points}) > 1:
                raise Invalid(f"{name}.points rows must all have {dims} coordinates")
            points = np.array(scan.points, dtype=np.float64)
            scans.append(point_cloud(
                name, scan.pose, points, range_max=scan.range_max, registration_sigma=scan.registration_sigma,
                dims=dims, limits=limits,
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
    _check_rays("body", shape[0], limits)
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
    """(N, 3) float64 points of a raw body: ``point_step`` bytes a point, x, y, z little-endian float32 first.

    Raw bytes do not say their layout, and guessing 12 bytes a point read a 16-byte-stride
    PointCloud2 (x, y, z, intensity) as 400 garbage points instead of 300 (issue 12): the stride
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
    _check_rays("body", len(body) // step, limits)
    if len(body) % step:
        raise Invalid(f"body: {len(body)} bytes is not a whole number of points of point_step {step} bytes")
    layout = np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3, "offsets": [0, 4, 8], "itemsize": step})
    records = np.frombuffer(body, dtype=layout)
    return np.column_stack([records["x"], records["y"], records["z"]]).astype(np.float64)


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


# ---------------------------------------------------------------- storage codec

#: A stored batch: this magic, a little-endian uint32 header length, a JSON header, then per scan its
#: float64 scalars and its values, raw little-endian. Batches stored before it are ``.npz`` files
#: (they start with ``PK``, the zip magic) and still decode.
_MAGIC = b"FRB\x01"
_HEADER_LENGTH = struct.Struct("<I")
_VALUE_DTYPES = {"<f4": np.dtype("<f4"), "<f8": np.dtype("<f8")}


def _compact(values: np.ndarray) -> np.ndarray:
    """float32 when that loses nothing (binary uploads, float32 drivers), else float64 (little-endian)."""
    values = np.asarray(values, dtype="<f8")
    with np.errstate(over="ignore", invalid="ignore"):  # too big for float32: then not exact anyway
        as32 = values.astype("<f4")
    # exact iff every value's bits come back from float32 unchanged (NaN payloads and -0.0 included)
    exact = bool(np.array_equal(as32.astype("<f8").view(np.uint64), values.view(np.uint64)))
    return as32 if exact else values


def _parts(scan: Scan) -> tuple[str, np.ndarray, np.ndarray]:
    if isinstance(scan, LaserScan):
        scalars = [*scan.pose, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max,
                   scan.registration_sigma]
        return "laser", np.array(scalars, dtype="<f8"), _compact(scan.ranges)
    return "cloud", np.array([*scan.origin, scan.range_max, scan.registration_sigma], dtype="<f8"), _compact(scan.points)


def encode(scans: Sequence[Scan]) -> bytes:
    """A validated batch as bytes that :func:`decode` turns back into equal scans (bit for bit).

    Framed raw arrays rather than an ``.npz``: writing a zip archive cost more than parsing the
    request (it ran for every batch, on the event loop for small bodies).
    """
    parts = [_parts(scan) for scan in scans]
    header = json.dumps({"scans": [
        {"kind": kind, "scalars": int(scalars.size), "dtype": values.dtype.str, "shape": list(values.shape)}
        for kind, scalars, values in parts
    ]}).encode()
    chunks = [_MAGIC, _HEADER_LENGTH.pack(len(header)), header]
    for _, scalars, values in parts:
        chunks.append(scalars.tobytes())
        chunks.append(np.ascontiguousarray(values).tobytes())
    return b"".join(chunks)


def _scan(kind: str, scalars: list[float], values: np.ndarray) -> Scan:
    if kind == "laser":
        x, y, theta, angle_min, increment, range_min, range_max, reg = scalars
        return LaserScan(pose=(x, y, theta), angle_min=angle_min, angle_increment=increment, ranges=values,
                         range_min=range_min, range_max=range_max, registration_sigma=reg,
                         max_rays=max(values.size, 1))
    *origin, range_max, reg = scalars
    return PointCloud(points=values, origin=tuple(origin), range_max=range_max, registration_sigma=reg,
                      max_rays=max(values.shape[0], 1))


class CorruptBatch(ValueError):
    """A stored batch whose bytes do not decode (the message says where)."""


_SCALARS = {"laser": (8,), "cloud": (4, 5)}  # laser: pose, angles, ranges, sigma; cloud: origin (2 or 3), max, sigma


def decode(payload: bytes) -> list[Scan]:
    """The scans of an :func:`encode` blob, or of a batch stored as ``.npz`` by an earlier version.

    Raises :class:`CorruptBatch` for bytes that are not such a blob, never reading past them.
    """
    try:
        if not payload.startswith(_MAGIC):
            return _decode_npz(payload)
        return _decode_framed(payload)
    except CorruptBatch:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure to decode is corruption, named as such
        raise CorruptBatch(f"stored batch does not decode: {type(exc).__name__}: {exc}") from exc


def _take(payload: bytes, offset: int, dtype: np.dtype, count: int) -> np.ndarray:
    if count < 0 or offset + count * dtype.itemsize > len(payload):
        raise CorruptBatch(f"stored batch is truncated or its header is wrong ({count} values at byte {offset})")
    return np.frombuffer(payload, dtype=dtype, count=count, offset=offset)


def _decode_framed(payload: bytes) -> list[Scan]:
    offset = len(_MAGIC)
    (length,) = _HEADER_LENGTH.unpack_from(payload, offset)
    offset += _HEADER_LENGTH.size
    if offset + length > len(payload):
        raise CorruptBatch("stored batch is truncated inside its header")
    header = json.loads(payload[offset:offset + length])
    offset += length
    scans: list[Scan] = []
    for item in header["scans"]:
        kind, count, shape = str(item["kind"]), int(item["scalars"]), tuple(int(n) for n in item["shape"])
        if count not in _SCALARS.get(kind, ()) or any(n < 0 for n in shape) or len(shape) != (1 if kind == "laser" else 2):
            raise CorruptBatch(f"stored batch has a malformed scan header: {item!r}")
        scalars = _take(payload, offset, np.dtype("<f8"), count)
        offset += scalars.nbytes
        values = _take(payload, offset, _VALUE_DTYPES[item["dtype"]], math.prod(shape)).reshape(shape)
        offset += values.nbytes
        scans.append(_scan(kind, scalars.tolist(), values.astype(np.float64)))
    if offset != len(payload):
        raise CorruptBatch(f"stored batch has {len(payload) - offset} bytes after its last scan")
    return scans


def _decode_npz(payload: bytes) -> list[Scan]:
    with np.load(io.BytesIO(payload), allow_pickle=False) as archive:
        kinds = [str(k) for k in archive["kinds"]]
        return [_scan(kind, archive[f"s{i}_scalars"].tolist(), archive[f"s{i}_values"].astype(np.float64))
                for i, kind in enumerate(kinds)]


# ---------------------------------------------------------------- the last scan, for the web page


@dataclass(frozen=True)
class ScanView:
    origin: list[float]
    endpoints: list[list[float]]
    hit: list[bool]


def scan_view(scan: Scan) -> ScanView:
    """Beam ends of a scan in the map frame, evenly thinned to at most ``MAX_VIEW_BEAMS`` of its rays.

    Made part by part (``fuzzyocc.maps.scan_parts``): the rays of a whole scan of millions of beams
    take about 150 bytes a beam (issue 11).
    """
    n = scan.beam_count
    rays_in_all = scan.usable(slice(0, n)) if isinstance(scan, LaserScan) else n
    step = max(1, math.ceil(rays_in_all / MAX_VIEW_BEAMS))
    ends, hit, seen = [], [], 0
    for part in scan_parts(scan):
        rays = scan.to_rays(beams=part)
        start = -seen % step  # this part's first ray to show: every step-th of the scan's rays
        ends.append(rays.endpoints[start::step])
        hit.append(rays.hit[start::step])
        seen += rays.ranges.size
    return ScanView(
        origin=[float(v) for v in rays.origin],
        endpoints=np.round(np.concatenate(ends), 4).tolist(),
        hit=np.concatenate(hit).tolist(),
    )
