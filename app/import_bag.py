"""``python -m app.import_bag``: a map from a ROS bag (ROS 1 ``.bag``, rosbag2 with mcap or sqlite3 storage).

    python -m app.import_bag BAG [--topic T ...] [--map-frame F] [--pose-topic T [--pose-frame F]]
                             [--cloud-range-max M] [--dimensions 2|3] [--resolution 0.05] [--margin 1]
                             [--every N] [--model fuzzy|bayes] [--png FILE] [--nav2 FILE.zip] [--npy FILE]
                             [--url http://127.0.0.1:8000 --map NAME [--api-key KEY] [--append] [--body cdr|json]]

A :class:`BagStream` reads the bag with rosbags: first ``/tf`` and ``/tf_static`` (or the pose topic)
into a :class:`fuzzyocc.tf.TransformBuffer`, then the LaserScan and PointCloud2 topics, in the order they
were recorded, one message at a time, so that scans are fused (or posted) batch by batch and the bag is
never held in memory. Without ``--origin`` (or a map to ``--append`` to) the command reads the bag
twice: once for the bounds of the placed scans (the grid), once to fuse them. Each message's sensor pose is ``T_map_frame`` at its ``header.stamp``, interpolated
along the chain of transforms from its ``header.frame_id`` to ``--map-frame``; a message the
transforms do not cover is skipped, and the summary counts why. Each message is converted by
:mod:`app.rosmsgs`, the code the service runs on a CDR body, so the three ways in (fused here,
posted as CDR bodies, posted as JSON batches) give the same map bit for bit.

``POST /maps/{name}/bags`` (``app/bag_upload.py``) reads an uploaded bag with a :class:`BagStream` too.
Progress goes to stderr, a one-line summary to stdout; errors exit 1 with a message.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import re
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, Self, TextIO
from urllib.parse import quote, urlencode

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.serde import SerdeError

from app import exports, rosmsgs
from app.batches import Limits, Scan
from app.config import Settings
from app.errors import ServiceError
from app.import_log import ImportFailed, ServiceClient, _non_negative, _positive, run_command
from app.rostypes import ns_of_ros_time
from app.schemas import DEFAULT_FRAME_ID
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, SensorModel
from fuzzyocc.tf import LookupFailed, Transform, TransformBuffer

PROG = "fuzzyrisk-import-bag"
TF_TOPICS = {"/tf": False, "/tf_static": True, "tf": False, "tf_static": True}  # topic -> static
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry")
#: A PointCloud2 has no range_max; without ``--cloud-range-max`` points beyond this are no-returns.
DEFAULT_CLOUD_RANGE_MAX_M = 100.0
#: What the service allows by default (FUZZYRISK_MAX_RAYS_PER_SCAN), for scans fused here.
DEFAULT_LIMITS = Limits(max_scans=Settings.model_fields["max_scans_per_batch"].default,
                        max_rays=Settings.model_fields["max_rays_per_scan"].default)
_BAG_ERRORS = (AnyReaderError, Ros1ReaderError, Ros2ReaderError, SerdeError)


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
    pose: rosmsgs.SensorPose
    sensor: rosmsgs.SensorScan | None  # None unless kept (``keep_sensor``): the scan holds the same numbers
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
    wanted = [c for c in reader.connections if c.msgtype in rosmsgs.MSGTYPES]
    if options.topics:
        named = {c.topic: c for c in reader.connections}
        for topic in options.topics:
            if topic not in named:
                raise BagUnreadable(f"the bag has no topic {topic!r}; its scan topics: "
                                    f"{', '.join(sorted({c.topic for c in wanted})) or 'none'}")
            if named[topic].msgtype not in rosmsgs.MSGTYPES:
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
        except _BAG_ERRORS as exc:
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
                    cdr = bytes(raw) if reader.is2 else rosmsgs.encode(msg, connection.msgtype)
                self.placed += 1
                yield BagScan(connection.topic, connection.msgtype, stamp, pose,
                              sensor if self.keep_sensor else None, scan, cdr)
        except _BAG_ERRORS as exc:
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
           name: str, skipped: Counter[str]) -> tuple[int, rosmsgs.SensorPose, rosmsgs.SensorScan, Scan] | None:
    """(stamp, pose, what it is, the scan) of one message, or None with the reason counted in ``skipped``."""
    stamp = ns_of_ros_time(msg.header.stamp)
    try:
        pose = rosmsgs.SensorPose.of(buffer.lookup(options.map_frame, msg.header.frame_id, stamp))
    except LookupFailed as exc:
        skipped[exc.reason] += 1
        return None
    range_max = options.cloud_range_max if msgtype == rosmsgs.POINT_CLOUD2 else None
    try:
        sensor = rosmsgs.sensor_scan(msg, msgtype, pose, dims=dims, limits=limits, range_max=range_max, name=name)
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


# ---------------------------------------------------------------- the command


class Progress:
    """A line on a stream at most once a second, and the last one (``final``)."""

    def __init__(self, stream: TextIO, started: float, every_s: float = 1.0) -> None:
        self.stream, self.started, self.every_s = stream, started, every_s
        self._last = -math.inf

    def __call__(self, what: str, done: int, total: int, *, final: bool = False) -> None:
        now = time.perf_counter()
        if now - self._last >= self.every_s or final:
            self._last = now
            print(f"{PROG}: {done}/{total} {what}, {now - self.started:.1f} s", file=self.stream, flush=True)


@dataclasses.dataclass
class _Fused:
    """What the second pass did: scans fused (or posted) and their rays."""

    scans: int = 0
    rays: int = 0


#: Fuses (or posts) one batch of placed scans; returns the rays fused.
_Sink = Callable[[list[BagScan]], int]


def _in_process(args: argparse.Namespace, spec: GridSpec) -> tuple[_Sink, Callable[[], str]]:
    """Fuse each batch into a map held here; at the end, write the outputs asked for."""
    occupancy: FuzzyMap | BayesMap = FuzzyMap(spec) if args.model == "fuzzy" else BayesMap(spec)

    def fuse(batch: list[BagScan]) -> int:
        return int(occupancy.integrate_batch([s.scan for s in batch]).rays)

    def finish() -> str:
        risk, observed = occupancy.risk(), occupancy.observed()
        if args.png or args.nav2:
            flat, seen = (risk, observed) if spec.ndim == 2 else exports.project_z(
                risk, observed, origin_z=spec.origin[2], resolution=spec.resolution)
            if args.png:
                text = {"source": args.bag.name, "resolution": repr(spec.resolution),
                        "origin": repr(list(spec.origin))}
                args.png.write_bytes(exports.risk_png(flat, seen, scale=args.scale, text=text))
            if args.nav2:
                args.nav2.write_bytes(exports.nav2_zip(flat, seen, resolution=spec.resolution,
                                                       origin_xy=(spec.origin[0], spec.origin[1]),
                                                       mode=args.nav2_mode, image_format=args.nav2_format))
        if args.npy:
            args.npy.write_bytes(exports.npy_bytes(np.asarray(risk, dtype=np.float32)))
        return f"{args.model} map in-process"

    return fuse, finish


def _existing_map(client: ServiceClient, name: str) -> dict[str, Any] | None:
    """The service's MapInfo of ``name``, or None when it has no such map."""
    status, data = client.call("GET", f"/maps/{quote(name, safe='')}", ok=(200, 404))
    return dict(json.loads(data)) if status == 200 else None


def _spec_of(info: Mapping[str, Any]) -> GridSpec:
    return GridSpec(origin=tuple(info["origin"]), size=tuple(info["size"]), resolution=info["resolution"],
                    max_cells=2**62)  # the service's map, whatever this side's default limit


def _create(client: ServiceClient, args: argparse.Namespace, spec: GridSpec, map_frame: str) -> dict[str, Any]:
    """Create the map (in ``--map-frame``: its ``frame_id``); a name taken without ``--append`` fails."""
    request = {"name": args.map, "dimensions": spec.ndim, "resolution": spec.resolution, "origin": list(spec.origin),
               "size": list(spec.size), "model": args.model, "sensor": dataclasses.asdict(SensorModel()),
               "frame_id": map_frame}
    status, data = client.call("POST", "/maps", json.dumps(request).encode(), ok=(201, 409))
    if status == 201:
        return dict(json.loads(data))
    raise ImportFailed(f"a map named {args.map!r} exists on {client.url}: pass --append to add the scans to it, "
                       "or choose another --map")


def _through_service(args: argparse.Namespace, client: ServiceClient,
                     info: dict[str, Any]) -> tuple[_Sink, Callable[[], str]]:
    """Post each batch (one CDR body a scan, or one JSON batch); at the end, download the outputs asked for."""
    name = quote(args.map, safe="")
    version = info.get("version")
    fused = 0

    def post(target: str, body: bytes, content_type: str) -> int:
        nonlocal version, fused
        try:
            _, data = client.call("POST", target, body, content_type=content_type)
        except ImportFailed as exc:
            raise ImportFailed(f"{exc} ({fused} scans were fused into {args.map!r} before this request)") from None
        result = json.loads(data)
        version, fused = result["version"], fused + int(result["scans_fused"])
        return int(result["rays"])

    def send(batch: list[BagScan]) -> int:
        if args.body == "json":
            assert all(s.sensor is not None for s in batch)  # kept for --body json
            body = json.dumps({"scans": [s.sensor.to_json() for s in batch]}).encode()  # type: ignore[union-attr]
            return post(f"/maps/{name}/scans", body, "application/json")
        rays = 0
        for s in batch:
            query = s.pose.query()
            if s.msgtype == rosmsgs.POINT_CLOUD2:
                query["range_max"] = args.cloud_range_max
            assert s.cdr is not None
            rays += post(f"/maps/{name}/scans?{urlencode(query)}", s.cdr, rosmsgs.media_type(s.msgtype))
        return rays

    def finish() -> str:
        downloads = [
            (args.png, f"/maps/{name}/risk?" + urlencode({"format": "png", "scale": args.scale})),
            (args.nav2, f"/maps/{name}/export/nav2?" + urlencode({"mode": args.nav2_mode,
                                                                  "format": args.nav2_format})),
            (args.npy, f"/maps/{name}/risk?format=npy"),
        ]
        for path, target in downloads:
            if path:
                path.write_bytes(client.call("GET", target)[1])
        return f"{info.get('model', args.model)} map {args.map!r} version {version} on {client.url}"

    return send, finish


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Build a fuzzy occupancy map from the LaserScan and PointCloud2 topics of a ROS bag "
        "(ROS 1 .bag; rosbag2 directory, .mcap or .db3), placed by /tf and /tf_static (or a pose topic), "
        "in-process (default) or through a running service (--url, --map).")
    p.add_argument("bag", type=Path, help="the bag: a ROS 1 .bag file, a rosbag2 directory, or its .mcap / .db3 file")
    r = p.add_argument_group("what to read")
    r.add_argument("--topic", action="append", default=[], metavar="T", dest="topics",
                   help="a LaserScan or PointCloud2 topic to map (repeatable; default: all of them)")
    r.add_argument("--map-frame", default=None,
                   help="the frame the map is in: the scans are placed in it, and a map created on the service "
                        f"gets it as its frame_id (default: an --append map's own frame_id, else {DEFAULT_FRAME_ID})")
    r.add_argument("--pose-topic", metavar="T", help="place the sensor by this PoseStamped, "
                   "PoseWithCovarianceStamped or Odometry topic instead of /tf for its frame")
    r.add_argument("--pose-frame", default="base_link",
                   help="the frame a PoseStamped pose topic places (default base_link; Odometry names its own)")
    r.add_argument("--cloud-range-max", type=_positive(float), default=DEFAULT_CLOUD_RANGE_MAX_M, metavar="M",
                   help="a PointCloud2's range, metres: points beyond are no-returns "
                        f"(default {DEFAULT_CLOUD_RANGE_MAX_M:g})")
    r.add_argument("--every", type=_positive(int), default=1, metavar="N", help="take every Nth scan (default 1)")
    g = p.add_argument_group("map")
    g.add_argument("--dimensions", type=int, choices=(2, 3), default=None,
                   help="2 or 3 (default: 3 if a PointCloud2 topic is read, else 2)")
    g.add_argument("--resolution", type=_positive(float), default=0.05, help="cell edge, metres (default 0.05)")
    g.add_argument("--margin", type=_non_negative, default=1.0,
                   help="padding around the sensor positions and hits, metres (default 1)")
    g.add_argument("--origin", type=float, nargs="+", metavar="X",
                   help="the map's corner (x y [z]), metres, with --size: a fixed box instead of the data's")
    g.add_argument("--size", type=_positive(float), nargs="+", metavar="W", help="the map's extent (x y [z]), metres")
    g.add_argument("--model", choices=("fuzzy", "bayes"), default="fuzzy", help="map model (default fuzzy)")
    g.add_argument("--batch", type=_positive(int), default=32,
                   help="scans per fusion batch / JSON request (default 32)")
    o = p.add_argument_group("output")
    o.add_argument("--png", type=Path, help="write the risk picture (PNG; a 3-D map's max-risk projection) here")
    o.add_argument("--scale", type=_positive(int), default=1, help="PNG pixels per cell (default 1)")
    o.add_argument("--nav2", type=Path, metavar="FILE.zip", help="write a Nav2 map_server zip here")
    o.add_argument("--nav2-mode", choices=("trinary", "scale", "raw"), default="trinary", help="default trinary")
    o.add_argument("--nav2-format", choices=("pgm", "png"), default="pgm", help="default pgm")
    o.add_argument("--npy", type=Path, help="write the risk grid (float32 .npy) here")
    s = p.add_argument_group("through the service")
    s.add_argument("--url", help="the service, e.g. http://127.0.0.1:8000 (default: fuse in-process)")
    s.add_argument("--map", help="name of the map to create on the service")
    s.add_argument("--api-key", default=os.environ.get("FUZZYRISK_API_KEY") or None,
                   help="the service's API key (default: $FUZZYRISK_API_KEY)")
    s.add_argument("--append", action="store_true", help="add the scans to the map if it exists")
    s.add_argument("--body", choices=("cdr", "json"), default="cdr",
                   help="post each message as its CDR body with its pose (default), or JSON batches of --batch scans")
    return p


def _check_options(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.url and not args.map:
        p.error("--url needs --map NAME")
    if (args.origin is None) != (args.size is None) or (args.origin and len(args.origin) != len(args.size)):
        p.error("--origin and --size go together, with as many values each (2 for a 2-D map, 3 for a 3-D map)")
    if args.origin and args.dimensions and len(args.origin) != args.dimensions:
        p.error(f"--origin and --size need {args.dimensions} values for --dimensions {args.dimensions}")
    if not args.url and (args.map or args.append):
        p.error("--map and --append need --url (without it the map is built in-process)")
    if args.nav2 is not None:
        try:
            exports.check_nav2_format(args.nav2_mode, args.nav2_format)
        except ValueError as exc:
            p.error(f"--nav2-mode {args.nav2_mode} --nav2-format {args.nav2_format}: {exc}")
    for option in ("png", "nav2", "npy"):
        path = getattr(args, option)
        if path is not None and not path.parent.is_dir():
            p.error(f"--{option}: directory {str(path.parent)!r} does not exist")


def _dimensions(args: argparse.Namespace) -> int:
    if args.dimensions is not None:
        return int(args.dimensions)
    if args.origin is not None:
        return len(args.origin)
    try:
        with AnyReader([args.bag]) as reader:
            chosen = [c for c in reader.connections if c.msgtype in rosmsgs.MSGTYPES
                      and (not args.topics or c.topic in args.topics)]
    except _BAG_ERRORS as exc:
        raise BagUnreadable(f"{args.bag.name}: not a readable bag ({exc})") from None
    return 3 if any(c.msgtype == rosmsgs.POINT_CLOUD2 for c in chosen) else 2


def summary_reasons(skipped: Counter[str]) -> str:
    """``3 before the first transform odom -> base_link, 1 no usable beam``, most frequent first."""
    return ", ".join(f"{n} {why}" for why, n in skipped.most_common()) or "none"


def _run(args: argparse.Namespace) -> str:
    """Read the bag in two passes (the first only to size the map: without ``--origin`` or an existing map),
    fusing or posting each batch as it is read: the bag is never held in memory."""
    started = time.perf_counter()
    progress = Progress(sys.stderr, started)
    dims = _dimensions(args)
    client = ServiceClient(args.url, args.api_key) if args.url else None
    existing = _existing_map(client, args.map) if client is not None and args.append else None
    if existing is not None and existing["dimensions"] != dims:
        raise ImportFailed(f"map {args.map!r} on {args.url} is {existing['dimensions']}-D; pass --dimensions "
                           f"{existing['dimensions']} to append to it")
    # the frame the scans are placed in: as given, else the existing map's own, else the default
    map_frame = args.map_frame or (existing or {}).get("frame_id") or DEFAULT_FRAME_ID
    options = BagOptions(map_frame=map_frame, topics=tuple(args.topics), pose_topic=args.pose_topic,
                         pose_frame=args.pose_frame, cloud_range_max=args.cloud_range_max, every=args.every)
    max_cells = Settings.model_fields["max_map_cells"].default
    placed = ""
    if existing is not None:
        spec = _spec_of(existing)
    elif args.origin is not None:
        spec = GridSpec(origin=tuple(args.origin), size=tuple(args.size), resolution=args.resolution,
                        max_cells=max_cells)
    else:  # a first pass: the bounds of every placed scan, nothing kept
        with BagStream(args.bag, options, dims=dims, limits=DEFAULT_LIMITS,
                       progress=lambda done, total: progress("scan messages read (sizing the map)", done,
                                                             total)) as sizing:
            spec = grid_for((s.scan for s in sizing), dims, args.resolution, args.margin, max_cells)
            progress("scan messages read (sizing the map)", sizing.messages, sizing.total, final=True)
            placed = f"; {sizing.placed} placed"
    if client is None:
        send, finish = _in_process(args, spec)
    else:
        send, finish = _through_service(args, client, existing or _create(client, args, spec, map_frame))
    shape = " x ".join(str(n) for n in spec.shape)
    fused = _Fused()

    def reading(done: int, total: int) -> None:
        progress(f"scan messages read, {fused.scans} scans fused", done, total)

    with BagStream(args.bag, options, dims=dims, limits=DEFAULT_LIMITS, keep_cdr=client is not None and
                   args.body == "cdr", keep_sensor=client is not None and args.body == "json",
                   progress=reading) as bag:
        print(f"{PROG}: {args.bag.name}: {bag.total} scan messages on {', '.join(sorted(bag.topics))}, "
              f"{bag.transforms} transforms{placed}; map {shape} cells of {spec.resolution} m from "
              f"({', '.join(f'{v:g}' for v in spec.origin)}) in frame {map_frame}", file=sys.stderr, flush=True)
        for batch in bag.batches(args.batch):
            fused.rays += send(batch)
            fused.scans += len(batch)
        progress(f"scan messages read, {fused.scans} scans fused", bag.messages, bag.total, final=True)
        where = finish()
        elapsed = time.perf_counter() - started
        return (f"{args.bag.name}: {bag.messages} scan messages read, {fused.scans} fused, "
                f"{sum(bag.skipped.values())} skipped ({summary_reasons(bag.skipped)}); {fused.rays:,} rays; "
                f"{where}, {shape} cells of {spec.resolution} m; {elapsed:.1f} s "
                f"({fused.scans / max(elapsed, 1e-9):.0f} scans/s)")


def main(argv: list[str] | None = None) -> int:
    """Run the command; the exit code (0 done, 1 failed with a message, 2 bad options)."""
    parser = _parser()
    args = parser.parse_args(argv)
    _check_options(parser, args)
    return run_command(PROG, lambda: _run(args), args.bag)


if __name__ == "__main__":
    sys.exit(main())
