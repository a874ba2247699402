"""ROS bags read as placed scans: ROS 1 ``.bag``, rosbag2 with mcap or sqlite3 storage (rosbags' AnyReader).

A :class:`BagStream` reads the bag with rosbags: first ``/tf`` and ``/tf_static`` (or the pose topic)
into a :class:`fuzzyocc.tf.TransformBuffer`, then the LaserScan and PointCloud2 topics, in the order they
were recorded, one message at a time, so that scans are fused (or posted) batch by batch and the bag is
never held in memory. Each message's sensor pose is ``T_map_frame`` at its ``header.stamp``, interpolated
along the chain of transforms from its ``header.frame_id`` to the map frame; a message the transforms do not
cover is skipped, and :class:`BagRead` counts why. Each message is converted by :mod:`app.ros.messages_in`,
the code the service runs on a CDR body, so the three ways in (fused by ``python -m app.import_bag``,
posted as CDR bodies, uploaded to ``POST /maps/{name}/bags``) give the same map bit for bit.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, Self

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.serde import SerdeError

from app.ros import messages_in
from app.scans import Limits, Scan
from app.config import Settings
from app.errors import ServiceError
from app.ros.msgtypes import ns_of_ros_time
from fuzzyocc import GridSpec
from fuzzyocc.tf import LookupFailed, Transform, TransformBuffer

TF_TOPICS = {"/tf": False, "/tf_static": True, "tf": False, "tf_static": True}  # topic -> static
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry")
#: A PointCloud2 has no range_max; without ``--cloud-range-max`` points beyond this are no-returns.
DEFAULT_CLOUD_RANGE_MAX_M = 100.0
#: What the service allows by default (FUZZYRISK_MAX_RAYS_PER_SCAN), for scans fused here.
DEFAULT_LIMITS = Limits(max_scans=Settings.model_fields["max_scans_per_batch"].default,
                        max_rays=Settings.model_fields["max_rays_per_scan"].default)
BAG_ERRORS = (AnyReaderError, Ros1ReaderError, Ros2ReaderError, SerdeError)


class BagUnreadable(ValueError):
    """The bag cannot be opened or read, or names no usable topic (the message says which and why)."""


@dataclasses.dataclass(frozen=True)
class BagOptions:
    """What to read from a bag and how to place it."""

    map_frame: str = "map"
    topics: tuple[str, ...] = ()  # () = every LaserScan and PointCloud2 topic
    pose_topic: str | None = None  # PoseStamped, PoseWithCovarianceStamped or Odometry: T_frame_child over time
    pose_frame: str = "base_link"  # the child frame of a PoseStamped pose topic (Odometry names its own)
    cloud_range_max: float = DEFAULT_CLOUD_RANGE_MAX_M
    every: int = 1


@dataclasses.dataclass(frozen=True)
class BagScan:
    """One scan message of the bag, placed: its pose, the scan fused, and (if kept) what it is and its CDR bytes."""

    topic: str
    msgtype: str
    stamp_ns: int
    pose: messages_in.SensorPose
    sensor: messages_in.SensorScan | None  # None unless kept (``keep_sensor``): the scan holds the same numbers
    scan: Scan
    cdr: bytes | None


@dataclasses.dataclass
class BagRead:
    """The scans of a bag in recorded order, and the messages left out with why."""

    scans: list[BagScan]
    messages: int  # scan messages on the topics read
    topics: dict[str, str]  # topic -> message type
    skipped: Counter[str]
    transforms: int  # TF (or pose) samples buffered


def _reason(exc: ServiceError) -> str:
    # numbers differ from scan to scan ("tilted 12.3 degrees"): counted by the kind of refusal
    text = re.sub(r"^(\S+)\[\d+\]", r"\1", str(exc))  # "/scan[12]: ..." -> "/scan: ..."
    return "refused: " + re.sub(r"(?<![\w.-])-?\d+(?:\.\d+)?(?:e-?\d+)?(?![\w-])", "N", text)[:300]


def _pose_sample(msg: Any, msgtype: str, pose_frame: str) -> tuple[str, str, int, Transform]:
    pose = msg.pose if msgtype == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
    child = msg.child_frame_id if msgtype == "nav_msgs/msg/Odometry" else pose_frame
    p, q = pose.position, pose.orientation
    return (msg.header.frame_id, child, ns_of_ros_time(msg.header.stamp),
            Transform.of((p.x, p.y, p.z), (q.x, q.y, q.z, q.w)))


def _buffer(reader: Any, options: BagOptions) -> tuple[TransformBuffer, int]:
    """The transforms of the bag: ``/tf``, ``/tf_static``, and the pose topic's samples (which win for their child)."""
    tf_connections = [c for c in reader.connections if c.topic in TF_TOPICS]
    pose_connections = [c for c in reader.connections if c.topic == options.pose_topic]
    if options.pose_topic is not None:
        if not pose_connections:
            raise BagUnreadable(f"the bag has no topic {options.pose_topic!r} (--pose-topic)")
        if pose_connections[0].msgtype not in POSE_TYPES:
            raise BagUnreadable(f"--pose-topic {options.pose_topic} is a {pose_connections[0].msgtype}; "
                                f"it must be one of {', '.join(POSE_TYPES)}")
    poses: list[tuple[str, str, int, Transform]] = []
    tfs: list[tuple[str, str, int, Transform, bool]] = []
    # rosbags reads every topic when given no connections: a bag without /tf has none to read here
    wanted = tf_connections + pose_connections
    for connection, _, raw in reader.messages(connections=wanted) if wanted else ():
        msg = reader.deserialize(raw, connection.msgtype)
        if connection.topic == options.pose_topic:
            poses.append(_pose_sample(msg, connection.msgtype, options.pose_frame))
            continue
        static = TF_TOPICS[connection.topic]
        for t in msg.transforms:
            r, q = t.transform.translation, t.transform.rotation
            try:
                transform = Transform.of((r.x, r.y, r.z), (q.x, q.y, q.z, q.w))
            except ValueError:
                continue  # a NaN or zero quaternion in one sample: tf2 would refuse it too
            tfs.append((t.header.frame_id, t.child_frame_id, ns_of_ros_time(t.header.stamp), transform, static))
    buffer = TransformBuffer()
    for parent, child, stamp, transform in poses:
        buffer.add(parent, child, stamp, transform)
    posed = {child.lstrip("/") for _, child, _, _ in poses}
    for parent, child, stamp, transform, static in tfs:
        if child.lstrip("/") not in posed:  # the pose topic replaces /tf for its frame
            buffer.add(parent, child, stamp, transform, static=static)
    return buffer, len(poses) + len(tfs)


def _scan_connections(reader: Any, options: BagOptions) -> list[Any]:
    wanted = [c for c in reader.connections if c.msgtype in messages_in.MSGTYPES]
    if options.topics:
        named = {c.topic: c for c in reader.connections}
        for topic in options.topics:
            if topic not in named:
                raise BagUnreadable(f"the bag has no topic {topic!r}; its scan topics: "
                                    f"{', '.join(sorted({c.topic for c in wanted})) or 'none'}")
            if named[topic].msgtype not in messages_in.MSGTYPES:
                raise BagUnreadable(f"topic {topic} is a {named[topic].msgtype}; LaserScan and PointCloud2 are read")
        wanted = [c for c in wanted if c.topic in options.topics]
    if not wanted:
        raise BagUnreadable("the bag has no sensor_msgs/msg/LaserScan or sensor_msgs/msg/PointCloud2 topic")
    return wanted


class BagStream:
    """The placed scans of a bag, read as they are asked for, with what was read and left out so far.

    Opening reads the transforms (``/tf``, ``/tf_static``, the pose topic) into a buffer and checks
    the topics; iterating then reads the scan messages in recorded order, one message at a time
    (rosbags decompresses one chunk at a time), so that a caller fusing batch by batch holds one
    batch, never the bag. Used as a context manager (it closes the file); :func:`read_bag` keeps them all.

    ``keep_cdr`` keeps each message's ROS 2 CDR bytes (a ROS 2 bag's as recorded, a ROS 1 bag's
    re-serialized) for posting; ``keep_sensor`` what each is (``SensorScan``, for JSON). ``progress(done,
    total)`` is called as messages are read. Raises :class:`BagUnreadable` for a bag that cannot be read
    at all, on opening or part-way (a damaged chunk).
    """

    def __init__(self, path: Path, options: BagOptions, *, dims: int, limits: Limits, keep_cdr: bool = False,
                 keep_sensor: bool = False, progress: Callable[[int, int], None] | None = None) -> None:
        self.path, self.options, self.dims, self.limits = path, options, dims, limits
        self.keep_cdr, self.keep_sensor, self.progress = keep_cdr, keep_sensor, progress
        self.messages = 0  # scan messages read so far on the topics read
        self.placed = 0  # scans yielded so far
        self.total = 0  # scan messages on the topics read, as the bag's index counts them
        self.topics: dict[str, str] = {}  # topic -> message type
        self.skipped: Counter[str] = Counter()
        self.transforms = 0  # TF (or pose) samples buffered
        self._reader: Any = None
        self._buffer: TransformBuffer | None = None
        self._connections: list[Any] = []

    def __enter__(self) -> Self:
        try:
            self._reader = AnyReader([self.path])
            self._reader.open()
            self._buffer, self.transforms = _buffer(self._reader, self.options)
            self._connections = _scan_connections(self._reader, self.options)
        except BAG_ERRORS as exc:
            self.close()
            raise BagUnreadable(f"{self.path.name}: not a readable bag ({exc})") from None
        except BaseException:
            self.close()
            raise
        self.total = sum(c.msgcount for c in self._connections)
        self.topics = {c.topic: c.msgtype for c in self._connections}
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None and reader.stack is not None:  # opened (a failed open closes itself)
            reader.close()

    def __iter__(self) -> Iterator[BagScan]:
        reader, buffer, options = self._reader, self._buffer, self.options
        if reader is None or buffer is None:
            raise RuntimeError("BagStream: iterate inside 'with'")
        try:
            for connection, _, raw in reader.messages(connections=self._connections):
                self.messages += 1
                if self.progress is not None:
                    self.progress(self.messages, self.total)
                if (self.messages - 1) % options.every:
                    self.skipped[f"--every {options.every}"] += 1
                    continue
                try:
                    msg = reader.deserialize(raw, connection.msgtype)
                except (SerdeError, AnyReaderError) as exc:  # rosbags wraps a SerdeError in AnyReaderError
                    self.skipped[f"does not deserialize: {type(exc).__name__}"] += 1
                    continue
                placed = _place(msg, connection.msgtype, buffer, options, dims=self.dims, limits=self.limits,
                                name=f"{connection.topic}[{self.messages - 1}]", skipped=self.skipped)
                if placed is None:
                    continue
                stamp, pose, sensor, scan = placed
                cdr = None
                if self.keep_cdr:
                    cdr = bytes(raw) if reader.is2 else messages_in.encode(msg, connection.msgtype)
                self.placed += 1
                yield BagScan(connection.topic, connection.msgtype, stamp, pose,
                              sensor if self.keep_sensor else None, scan, cdr)
        except BAG_ERRORS as exc:
            raise BagUnreadable(f"{self.path.name}: not a readable bag ({exc})") from None

    def batches(self, size: int) -> Iterator[list[BagScan]]:
        """The placed scans in lists of at most ``size``, in recorded order."""
        scans = iter(self)
        while batch := list(itertools.islice(scans, size)):
            yield batch


def read_bag(path: Path, options: BagOptions, *, dims: int, limits: Limits, keep_cdr: bool = False,
             keep_sensor: bool = False, progress: Callable[[int, int], None] | None = None) -> BagRead:
    """Every scan message of the bag at ``path``, placed and converted for a map of ``dims`` dimensions, kept
    in memory (a small bag; :class:`BagStream` reads one batch at a time). Options as :class:`BagStream`'s."""
    with BagStream(path, options, dims=dims, limits=limits, keep_cdr=keep_cdr, keep_sensor=keep_sensor,
                   progress=progress) as stream:
        scans = list(stream)
        return BagRead(scans, stream.messages, stream.topics, stream.skipped, stream.transforms)


def _place(msg: Any, msgtype: str, buffer: TransformBuffer, options: BagOptions, *, dims: int, limits: Limits,
           name: str, skipped: Counter[str]) -> tuple[int, messages_in.SensorPose, messages_in.SensorScan, Scan] | None:
    """(stamp, pose, what it is, the scan) of one message, or None with the reason counted in ``skipped``."""
    stamp = ns_of_ros_time(msg.header.stamp)
    try:
        pose = messages_in.SensorPose.of(buffer.lookup(options.map_frame, msg.header.frame_id, stamp))
    except LookupFailed as exc:
        skipped[exc.reason] += 1
        return None
    range_max = options.cloud_range_max if msgtype == messages_in.POINT_CLOUD2 else None
    try:
        sensor = messages_in.sensor_scan(msg, msgtype, pose, dims=dims, limits=limits, range_max=range_max, name=name)
        if not sensor.usable:
            skipped["no usable beam (every reading invalid)"] += 1
            return None
        scan = sensor.to_scan(name, registration_sigma=0.0, dims=dims, limits=limits)
    except ServiceError as exc:
        skipped[_reason(exc)] += 1
        return None
    return stamp, pose, sensor, scan


def grid_for(scans: Iterable[Scan], dims: int, resolution: float, margin: float, max_cells: int) -> GridSpec:
    """The grid holding every sensor position and hit, padded by ``margin``, snapped to whole cells.

    No-returns do not widen it (they clear free space up to ``range_max`` and would stretch the
    map over space seen empty), as :func:`fuzzyocc.carmen.grid_for_scans` does for a log. The
    scans are looked at one at a time (a stream of them is fine): only the bounds are kept.
    """
    lower, upper = np.full(dims, np.inf), np.full(dims, -np.inf)
    for scan in scans:
        rays = scan.to_rays()
        points = np.concatenate([rays.origin[None, :], rays.endpoints[rays.hit]])[:, :dims]
        lower, upper = np.minimum(lower, points.min(axis=0)), np.maximum(upper, points.max(axis=0))
    if not np.isfinite(lower).all():
        raise ValueError("no scan could be placed: nothing to map (see the reasons skipped)")
    lower, upper = lower - margin, upper + margin
    origin = tuple(round(math.floor(v / resolution) * resolution, 10) for v in lower)
    cells = [max(1, math.ceil((u - o) / resolution - 1e-9)) for u, o in zip(upper, origin)]
    return GridSpec(origin=origin, size=tuple(n * resolution for n in cells), resolution=resolution,
                    max_cells=max_cells)
