"""ROS 2 messages in: ``sensor_msgs/msg/LaserScan`` and ``PointCloud2`` with a 3-D sensor pose, to our scans.

One conversion for every way a ROS message reaches a map: a CDR body posted to
``POST /maps/{name}/scans`` (:func:`from_cdr`), and the messages of a bag, imported in-process, posted
by ``python -m app.import_bag --url`` or uploaded to ``POST /maps/{name}/bags`` (:func:`sensor_scan`).
Messages are read with rosbags' typestore (``app.ros.msgtypes``, no ROS install); the sensor pose ``T_map_sensor`` (the
pose of the message's ``header.frame_id`` in the map frame, REP 103) comes with the message.

A message becomes a :class:`PlanarScan` or a :class:`SensorCloud`: exactly what a JSON batch carries
(``to_json``), so a message posted as CDR, as JSON or fused in-process gives the same map, bit for bit.
Its ``header.stamp`` goes with it (``stamp_ns``; a JSON scan's ``header.stamp``), as every message has one.

- **LaserScan on a 2-D map**: the scanner must be level (its z axis within ``fuzzyocc.tf.LEVEL_TOLERANCE_RAD`` of
  the map's +z or -z); ``theta`` is the heading of its x axis, and a scanner mounted upside down (z
  down, e.g. roll pi) sweeps the other way, so its angles are negated. Ranges as REP 117 says, as in
  JSON: ``+inf`` or ``>= range_max`` a no-return, ``-inf``, NaN and ``< range_min`` skipped.
- **LaserScan on a 3-D map** (any mounting, tilted too): beam ``i`` at ``a_i = angle_min + i *
  angle_increment`` becomes the sensor-frame point ``(r cos a_i, r sin a_i, 0)``; a no-return the
  point at ``2 * range_max`` along the beam (the cloud cuts it at ``range_max``: free space, no hit);
  skipped readings are left out. The scan-order handling of no-returns and the incidence estimate
  of a 2-D LaserScan do not apply to clouds.
- **PointCloud2**: ``x``, ``y``, ``z`` read by name from their fields (any of the eight datatypes,
  offsets, ``point_step``, ``row_step``, ``is_bigendian``), rows with a non-finite coordinate (an
  organised cloud's no-return) dropped whatever ``is_dense`` says. Little-endian float32 ``x y z``
  side by side, every lidar driver's layout, are read without a copy of the body: a strided view of
  ``data`` (a view of the body itself), the finite rows copied once. A 3-D map takes them with the
  3-D pose; a 2-D map takes them rotated into the map's axes and projected on its plane (z
  dropped), so filter heights first (``pointcloud_to_laserscan`` does) if the floor is in view.
  A PointCloud2 carries no ``range_max``: the caller gives one.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import ValidationError
from rosbags.serde import SerdeError
from scipy.spatial.transform import Rotation

from app.scans import Limits, Scan, check_rays, finite_rows, laser_scan, point_cloud
from app.errors import Invalid
from app.ros.msgtypes import ns_of_ros_time, ros_time_of_ns, typestore
from app.schemas import Pose2D, Pose3D, StampIn
from fuzzyocc import tf
from fuzzyocc.tf import Transform

LASER_SCAN = "sensor_msgs/msg/LaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
MSGTYPES = (LASER_SCAN, POINT_CLOUD2)


def media_type(msgtype: str) -> str:
    """The Content-Type of a CDR-serialized message: ``application/vnd.ros2.sensor_msgs.msg.LaserScan+cdr``.

    After MCAP's naming of the same payload (message encoding ``cdr``, schema ``sensor_msgs/msg/LaserScan``),
    the slashes made dots so that the name is one media type.
    """
    return f"application/vnd.ros2.{msgtype.replace('/', '.')}+cdr"


#: Accepted Content-Types (compared lower-case, as media types are case-insensitive) -> message type.
MEDIA_TYPES = {media_type(t).lower(): t for t in MSGTYPES}
#: Most fields a PointCloud2 may declare (drivers send 3 to 12); checked before the message is read.
MAX_POINT_FIELDS = 64
#: Query parameters a CDR body must not carry: the message itself holds them.
_FROM_MESSAGE = ("theta", "angle_min", "angle_increment", "range_min")
_POSE_PARAMS = ("x", "y", "z", "qx", "qy", "qz", "qw")
#: sensor_msgs/PointField datatypes -> numpy type codes (byte order added per message).
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_FLOAT32 = 7


# ---------------------------------------------------------------- the sensor pose


@dataclass(frozen=True)
class SensorPose:
    """``T_map_sensor``: position (metres) and unit quaternion ``[x, y, z, w]`` of the message's frame in the map."""

    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]

    @classmethod
    def of(cls, transform: Transform) -> SensorPose:
        x, y, z = (float(v) for v in transform.translation)
        qx, qy, qz, qw = (float(v) for v in transform.rotation.as_quat())
        return cls((x, y, z), (qx, qy, qz, qw))

    def query(self) -> dict[str, float]:
        """The query parameters that carry this pose with a CDR body."""
        return dict(zip(_POSE_PARAMS, (*self.position, *self.orientation)))


def pose_from_query(params: Mapping[str, Any], name: str = "query") -> SensorPose:
    """The pose of a CDR upload: ``x, y, z, qx, qy, qz, qw``, all seven required (no default orientation)."""
    given = [p for p in _FROM_MESSAGE if params.get(p) is not None]
    if given:
        raise Invalid(f"{name}: {', '.join(given)} come from the message in a ROS message body: drop them, and give "
                      "the sensor pose as x, y, z, qx, qy, qz, qw")
    missing = [p for p in _POSE_PARAMS if params.get(p) is None]
    if missing:
        raise Invalid(f"{name}: a ROS message body needs the sensor pose T_map_sensor (the pose of the message's "
                      f"frame_id in the map frame) as x, y, z, qx, qy, qz, qw; missing: {', '.join(missing)}")
    x, y, z, qx, qy, qz, qw = (float(params[p]) for p in _POSE_PARAMS)
    pose = SensorPose((x, y, z), (qx, qy, qz, qw))
    _pose3d(pose, name)  # a unit quaternion (within 1e-3), as a JSON pose
    return pose


def _pose3d(pose: SensorPose, name: str) -> Pose3D:
    try:
        return Pose3D(position=list(pose.position), orientation=list(pose.orientation))
    except ValidationError as exc:
        raise Invalid(f"{name}: {exc.errors()[0]['msg']}") from None


def _unit_quaternion(pose: SensorPose) -> np.ndarray:
    q = np.array(pose.orientation, dtype=np.float64)
    return q / np.linalg.norm(q)


def level_heading(pose: SensorPose, name: str) -> tuple[float, float]:
    """(theta, turn) of a level scanner: the heading of its x axis in the map, and +1 (z up) or -1 (z down).

    A scanner tilted beyond ``fuzzyocc.tf.LEVEL_TOLERANCE_RAD`` has no planar scan: ``Invalid`` naming ``name``.
    """
    try:
        return tf.level_heading(pose.orientation)
    except tf.NotLevel as exc:
        raise Invalid(f"{name}: the scanner is tilted {exc.degrees:.1f} degrees from level (its z axis against the "
                      f"map's vertical); a 2-D map takes a LaserScan only from a scanner level within "
                      f"{math.degrees(tf.LEVEL_TOLERANCE_RAD):g} degrees (z up, or down when mounted upside down): "
                      "create a 3-D map for a tilted scanner") from None


# ---------------------------------------------------------------- what a message becomes


def _range_token(r: float) -> float | str:
    if math.isnan(r):
        return "nan"
    if math.isinf(r):
        return "inf" if r > 0 else "-inf"
    return r


def stamp_header(stamp_ns: int | None) -> dict[str, Any]:
    """The ``header`` of a JSON scan (``ScanHeader``) taken at ``stamp_ns``; empty for an unstamped one."""
    return {} if stamp_ns is None else {"header": {"stamp": ros_time_of_ns(stamp_ns)}}


def message_stamp_ns(msg: Any, name: str) -> int:
    """A message's ``header.stamp`` as Unix nanoseconds; ``Invalid`` for one a JSON scan may not carry either
    (negative, ``nanosec`` past a second)."""
    stamp = {"sec": int(msg.header.stamp.sec), "nanosec": int(msg.header.stamp.nanosec)}
    try:
        StampIn.model_validate(stamp)
    except ValidationError as exc:
        error = exc.errors()[0]
        raise Invalid(f"{name}.header.stamp.{error['loc'][0]}: {error['msg']}, got {stamp}") from None
    return ns_of_ros_time(stamp)


@dataclass(frozen=True)
class PlanarScan:
    """A LaserScan for a 2-D map, as a JSON batch carries it (``LaserScanIn``)."""

    pose: Pose2D
    angle_min: float
    angle_increment: float
    ranges: np.ndarray
    range_min: float
    range_max: float
    stamp_ns: int | None = None

    def to_scan(self, name: str, *, registration_sigma: float, dims: int, limits: Limits) -> Scan:
        return laser_scan(
            name, self.pose, angle_min=self.angle_min, angle_increment=self.angle_increment, ranges=self.ranges,
            range_min=self.range_min, range_max=self.range_max, registration_sigma=registration_sigma, dims=dims,
            limits=limits, stamp_ns=self.stamp_ns,
        )

    def to_json(self, registration_sigma: float = 0.0) -> dict[str, Any]:
        # json writes the shortest repr that reads back to the same float64: the service fuses these numbers
        return {"pose": self.pose.model_dump(), "angle_min": self.angle_min, "angle_increment": self.angle_increment,
                "ranges": [_range_token(r) for r in self.ranges.tolist()], "range_min": self.range_min,
                "range_max": self.range_max, "registration_sigma": registration_sigma,
                **stamp_header(self.stamp_ns)}

    @property
    def usable(self) -> bool:
        """Whether any beam is a hit or a no-return (REP 117), i.e. whether the scan says anything."""
        return bool(np.any(self.ranges >= self.range_min))


@dataclass(frozen=True)
class SensorCloud:
    """Sensor-frame points with the sensor pose, as a JSON batch carries them (``PointCloudIn``)."""

    pose: Pose2D | Pose3D
    points: np.ndarray
    range_max: float
    stamp_ns: int | None = None

    def to_scan(self, name: str, *, registration_sigma: float, dims: int, limits: Limits) -> Scan:
        return point_cloud(name, self.pose, self.points, range_max=self.range_max,
                           registration_sigma=registration_sigma, dims=dims, limits=limits, stamp_ns=self.stamp_ns)

    def to_json(self, registration_sigma: float = 0.0) -> dict[str, Any]:
        finite = self.points[np.isfinite(self.points).all(axis=1)]
        return {"pose": self.pose.model_dump(), "points": finite.tolist(), "range_max": self.range_max,
                "registration_sigma": registration_sigma, **stamp_header(self.stamp_ns)}

    @property
    def usable(self) -> bool:
        return bool(np.isfinite(self.points).all(axis=1).any())


SensorScan = PlanarScan | SensorCloud


def _finite(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise Invalid(f"{name} must be finite, got {value}")
    return value


def _laser(msg: Any, pose: SensorPose, name: str, dims: int, limits: Limits) -> SensorScan:
    ranges32 = np.asarray(msg.ranges)
    check_rays(f"{name}.ranges", ranges32.size, limits)
    with np.errstate(invalid="ignore"):  # a signalling NaN is a NaN reading all the same
        ranges = ranges32.astype(np.float64)
    angle_min, increment = float(msg.angle_min), float(msg.angle_increment)
    range_min, range_max = float(msg.range_min), float(msg.range_max)
    if dims == 2:
        theta, turn = level_heading(pose, name)
        return PlanarScan(Pose2D(x=pose.position[0], y=pose.position[1], theta=theta), turn * angle_min,
                          turn * increment, ranges, range_min, range_max)
    # a 3-D map: the beams as sensor-frame points, checked as LaserScan checks them
    angle_min, increment = _finite(f"{name}.angle_min", angle_min), _finite(f"{name}.angle_increment", increment)
    range_min, range_max = _finite(f"{name}.range_min", range_min), _finite(f"{name}.range_max", range_max)
    if not 0.0 <= range_min < range_max:
        raise Invalid(f"{name}: range_max must be greater than range_min >= 0, got range_min={range_min}, "
                      f"range_max={range_max}")
    keep = ranges >= range_min  # False for NaN and -inf: skipped (REP 117)
    angles = angle_min + np.flatnonzero(keep) * increment
    r = ranges[keep]
    r = np.where(r >= range_max, 2.0 * range_max, r)  # a no-return: past range_max, where the cloud cuts it
    points = np.column_stack([r * np.cos(angles), r * np.sin(angles), np.zeros(r.size)])
    return SensorCloud(_pose3d(pose, name), points, range_max)


def _fields_by_name(msg: Any) -> dict[str, Any]:
    """A PointCloud2's fields by name (the first of a name, as a driver that repeats one means it)."""
    by_name: dict[str, Any] = {}
    for f in msg.fields:
        by_name.setdefault(str(f.name), f)
    return by_name


def _field_dtype(msg: Any, by_name: Mapping[str, Any], name: str, dims: int) -> np.dtype:
    """The structured dtype of one point: x, y (and z) at their offsets, ``point_step`` bytes long."""
    order = ">" if msg.is_bigendian else "<"
    step = int(msg.point_step)
    wanted = ("x", "y", "z") if dims == 3 or "z" in by_name else ("x", "y")
    missing = [n for n in wanted if n not in by_name]
    if missing:
        raise Invalid(f"{name}: the PointCloud2 has no field {', '.join(missing)} (its fields: "
                      f"{', '.join(by_name) or 'none'}); x, y and z are read by name")
    formats, offsets = [], []
    for n in wanted:
        f = by_name[n]
        code = _FIELD_TYPES.get(int(f.datatype))
        if code is None:
            raise Invalid(f"{name}: field {n} has datatype {f.datatype}, not one of sensor_msgs/PointField's 1..8")
        if int(f.count) < 1:
            raise Invalid(f"{name}: field {n} has count {f.count}; it must hold at least one value")
        size = np.dtype(code).itemsize
        if int(f.offset) + size > step:
            raise Invalid(f"{name}: field {n} (offset {f.offset}, {size} bytes) does not fit in point_step {step}")
        formats.append(order + code)
        offsets.append(int(f.offset))
    return np.dtype({"names": list(wanted), "formats": formats, "offsets": offsets, "itemsize": step})


def _xyz_float32(msg: Any, by_name: Mapping[str, Any], data: np.ndarray, height: int, width: int) -> np.ndarray | None:
    """A (height, width, 3) float32 view of the points' x, y, z in ``data`` when they are little-endian float32 side
    by side, at any offset, ``point_step`` and ``row_step`` (every lidar driver's layout); None for another layout.

    The sizes are checked (``cloud_points``): the view reads nothing outside ``data``.
    """
    fields = [by_name.get(n) for n in ("x", "y", "z")]
    if msg.is_bigendian or any(f is None or int(f.datatype) != _FLOAT32 or int(f.count) < 1 for f in fields):
        return None
    offset = int(fields[0].offset)
    if [int(f.offset) for f in fields] != [offset, offset + 4, offset + 8] or offset + 12 > int(msg.point_step):
        return None
    return np.ndarray((height, width, 3), dtype="<f4", buffer=data, offset=offset,
                      strides=(int(msg.row_step), int(msg.point_step), 4))


def cloud_points(msg: Any, name: str, dims: int, limits: Limits) -> np.ndarray:
    """(N, 3) sensor-frame points of a PointCloud2, row by row, without the rows with a non-finite coordinate (an
    organised cloud's no-returns, whatever ``is_dense`` says); z is 0 for a 2-D cloud on a 2-D map.

    Little-endian float32 x, y, z side by side (``_xyz_float32``) are viewed in place and copied once, to float32
    (fuzzyocc converts them to float64 as it places them); any other layout is read field by field to float64.
    Every size is checked before a byte of ``data`` is read: the point count against the limit,
    ``point_step`` against the fields, ``row_step`` against the row, ``data`` against ``row_step * height``.
    """
    height, width = int(msg.height), int(msg.width)
    check_rays(f"{name}.points", height * width, limits)  # Python ints: 2**32 squared cannot overflow
    step, row_step, data = int(msg.point_step), int(msg.row_step), np.asarray(msg.data, dtype=np.uint8)
    if height * width == 0:
        return np.zeros((0, 3))
    if step <= 0:
        raise Invalid(f"{name}: point_step must be positive, got {step}")
    if row_step < width * step:
        raise Invalid(f"{name}: row_step {row_step} is less than width {width} x point_step {step}")
    if data.size != row_step * height:
        raise Invalid(f"{name}: data holds {data.size} bytes, but row_step {row_step} x height {height} is "
                      f"{row_step * height}: the message is truncated or its sizes are wrong")
    by_name = _fields_by_name(msg)
    dtype = _field_dtype(msg, by_name, name, dims)  # point_step is at most the data's size now: numpy takes it
    xyz = _xyz_float32(msg, by_name, data, height, width)
    if xyz is not None:
        return finite_rows(xyz)
    grid = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, step))
    with np.errstate(invalid="ignore"):  # a signalling NaN marks a no-return all the same
        columns = [grid[n].astype(np.float64).ravel() for n in dtype.names or ()]
    if len(columns) == 2:
        columns.append(np.zeros(height * width))
    return finite_rows(np.column_stack(columns))


def sensor_scan(msg: Any, msgtype: str, pose: SensorPose, *, dims: int, limits: Limits,
                range_max: float | None = None, name: str = "body") -> SensorScan:
    """What a LaserScan or PointCloud2 message taken at ``pose`` is on a map of ``dims`` dimensions.

    ``range_max`` is a PointCloud2's (the message has none); a LaserScan's is its own. The scan is stamped with
    the message's ``header.stamp``.
    Raises ``Invalid`` (422) or ``TooLarge`` (413) with a message that says what to change.
    """
    scan = _unstamped(msg, msgtype, pose, dims=dims, limits=limits, range_max=range_max, name=name)
    return dataclasses.replace(scan, stamp_ns=message_stamp_ns(msg, name))


def _unstamped(msg: Any, msgtype: str, pose: SensorPose, *, dims: int, limits: Limits,
               range_max: float | None, name: str) -> SensorScan:
    if msgtype == LASER_SCAN:
        return _laser(msg, pose, name, dims, limits)
    if msgtype != POINT_CLOUD2:
        raise Invalid(f"{name}: {msgtype} is not read here; send {' or '.join(MSGTYPES)}")
    if range_max is None:
        raise Invalid(f"{name}: a PointCloud2 carries no range_max: give the sensor's (range_max in the query), "
                      "points beyond it clear free space up to it")
    points = cloud_points(msg, name, dims, limits)
    if dims == 3:
        return SensorCloud(_pose3d(pose, name), points, float(range_max))
    # a 2-D map: rotated into the map's axes as PointCloud.from_sensor_frame rotates (in float64), then z dropped
    points = np.asarray(points, dtype=np.float64)
    rotated = Rotation.from_quat(_unit_quaternion(pose)).apply(points) if points.size else points
    return SensorCloud(Pose2D(x=pose.position[0], y=pose.position[1], theta=0.0), rotated[:, :2], float(range_max))


# ---------------------------------------------------------------- CDR bodies


def _cloud_counts(body: bytes) -> tuple[int, int, int] | None:
    """(height, width, number of fields) of a CDR PointCloud2, read from its first bytes; None if too short.

    Read before rosbags reads the message, so that a body claiming millions of fields or points is
    refused before any work (rosbags would build one object per field).
    """
    try:
        order = "<" if body[1] == 1 else ">"
        (length,) = struct.unpack_from(order + "I", body, 12)  # after the encapsulation header and the stamp
        pos = 4 + ((8 + 4 + length + 3) & ~3)  # the frame_id's bytes, then aligned to 4 (CDR aligns from byte 4)
        return struct.unpack_from(order + "III", body, pos)
    except (IndexError, struct.error):
        return None


def decode(body: bytes, msgtype: str, name: str = "body") -> Any:
    """The message of a CDR body (``serialize_message``'s or rosbags' ``serialize_cdr``'s bytes)."""
    try:
        # a memoryview: rosbags slices the body (a bytes slice is a copy of all of it) and views its arrays in place
        return typestore().deserialize_cdr(memoryview(body), msgtype)
    except SerdeError as exc:
        raise Invalid(f"{name}: not a CDR-serialized {msgtype} ({exc}): send the bytes "
                      "rclpy.serialization.serialize_message writes, with the Content-Type of their type") from None


def encode(msg: Any, msgtype: str) -> bytes:
    """The CDR bytes of a message of any distribution's types (a ROS 1 bag's too): rebuilt with ROS 2 types.

    A ROS 1 header has a ``seq`` that ROS 2's has not, so a ROS 1 message is copied field by field.
    """
    store = typestore()
    header = store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=int(msg.header.stamp.sec),
                                                          nanosec=int(msg.header.stamp.nanosec)),
        frame_id=str(msg.header.frame_id))
    if msgtype == LASER_SCAN:
        out = store.types[LASER_SCAN](
            header=header, angle_min=msg.angle_min, angle_max=msg.angle_max, angle_increment=msg.angle_increment,
            time_increment=msg.time_increment, scan_time=msg.scan_time, range_min=msg.range_min,
            range_max=msg.range_max, ranges=np.asarray(msg.ranges, dtype=np.float32),
            intensities=np.asarray(msg.intensities, dtype=np.float32))
    else:
        field_type = store.types["sensor_msgs/msg/PointField"]
        fields = [field_type(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in msg.fields]
        out = store.types[POINT_CLOUD2](
            header=header, height=msg.height, width=msg.width, fields=fields, is_bigendian=msg.is_bigendian,
            point_step=msg.point_step, row_step=msg.row_step, data=np.asarray(msg.data, dtype=np.uint8),
            is_dense=msg.is_dense)
    return bytes(store.serialize_cdr(out, msgtype))


def from_cdr(body: bytes, media: str, params: Mapping[str, Any], dims: int,
             limits: Limits) -> list[Scan]:
    """The one scan of a CDR body of Content-Type ``media`` (a key of ``MEDIA_TYPES``), pose in ``params``."""
    msgtype = MEDIA_TYPES[media]
    pose = pose_from_query(params)
    range_max = params.get("range_max")
    if msgtype == LASER_SCAN and range_max is not None:
        raise Invalid("query: range_max comes from the LaserScan message: drop it")
    if params.get("point_step") is not None:
        raise Invalid("query: point_step is for raw float32 points; a PointCloud2 says its own")
    counts = _cloud_counts(body) if msgtype == POINT_CLOUD2 else None
    # counts the body could not hold are not a PointCloud2's (other bytes, another type): rosbags says so
    if counts is not None and counts[0] * counts[1] <= len(body) and counts[2] <= len(body):
        height, width, fields = counts
        check_rays("body.points", height * width, limits)
        if fields > MAX_POINT_FIELDS:
            raise Invalid(f"body: the PointCloud2 declares {fields} fields, more than {MAX_POINT_FIELDS}")
    msg = decode(body, msgtype)
    scan = sensor_scan(msg, msgtype, pose, dims=dims, limits=limits, range_max=range_max)
    return [scan.to_scan("body", registration_sigma=float(params.get("registration_sigma") or 0.0), dims=dims,
                         limits=limits)]
