"""The batch log's record: a batch as the bytes stored, and back, bit for bit.

A batch is checked scans, a ``Prior`` (a saved map's cells, a map's first batch when it is
imported), or an edit (``Clear``: a region set back to never observed; ``SetForget``: the map's
``forget_beyond`` from then on), replayed in its place among the scans. Storage keeps these bytes opaque (versioned payloads with their checksums); the maps
write them before a batch is applied (``app.maps.ingest``, ``app.maps.writepath``) and replay them
at a restart (``app.maps.stored``).
"""

from __future__ import annotations

import io
import json
import math
import struct
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from app.scans import Scan
from fuzzyocc import LaserScan, PointCloud


@dataclass(frozen=True)
class Prior:
    """A saved map's cells as a batch: ``levels`` (int8 of the map's shape) for ``OccupancyMap.integrate_prior``.

    Each cell reads as if ``|level|`` scans had agreed on it (hits above 0, pass-throughs below),
    ``PRIOR_UNSEEN`` never observed. It has no pose and counts no scan: re-placing a map's scans
    (a corrected trajectory) leaves it as it is.
    """

    levels: np.ndarray


@dataclass(frozen=True)
class Clear:
    """A region set back to never observed (``OccupancyMap.clear``): the cells from the one containing ``low`` to the
    one containing ``high``, metres."""

    low: tuple[float, ...]
    high: tuple[float, ...]


@dataclass(frozen=True)
class SetForget:
    """The map's ``forget_beyond`` from this batch on (metres; None: keep everything)."""

    metres: float | None


@dataclass(frozen=True)
class Reposed:
    """The map rebuilt at a corrected trajectory (``correction``, its id): the scans of versions up to ``through``
    were given new poses (``scans`` of them), stored with their batches; the restart snapshot written with this record
    is the rebuilt map. Replayed as nothing: the batches before it replay at their new poses already."""

    correction: str
    through: int
    scans: int


#: An edit of a map, logged and replayed in its place among the scans.
Edit = Clear | SetForget | Reposed
#: What a batch record holds.
Batch = list[Scan] | Prior | Edit

#: A stored batch: this magic, a little-endian uint32 header length, a JSON header, then per scan its
#: float64 scalars and its values, raw little-endian. The header's entry of a stamped scan holds its
#: ``stamp_ns`` (an integer: JSON keeps it exact); records written before stamps have none, and decode
#: as unstamped. Batches stored before it are ``.npz`` files (they start with ``PK``, the zip magic) and
#: still decode, unstamped.
_MAGIC = b"FRB\x01"
#: A stored prior: this magic, the header as a batch's (``{"shape": [nx, ny]}``), then the levels deflated
#: (zlib): a saved map is mostly a few levels in long runs.
_PRIOR_MAGIC = b"FRP\x01"
#: A stored edit: this magic, then its JSON (floats written as Python's repr: read back bit for bit).
_EDIT_MAGIC = b"FRE\x01"
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
    if scan.sensor_points is not None and scan.sensor_pose is not None:
        # as taken: its sensor-frame points and pose, placed again at decode by the same arithmetic (a corrected
        # pose places them anew; float32 points of a driver stay float32)
        scalars = [*scan.sensor_pose, scan.range_max, scan.registration_sigma]
        return "sensor_cloud", np.array(scalars, dtype="<f8"), _compact(scan.sensor_points)
    return "cloud", np.array([*scan.origin, scan.range_max, scan.registration_sigma], dtype="<f8"), _compact(scan.points)


def encode(scans: Sequence[Scan]) -> bytes:
    """A validated batch as bytes that :func:`decode` turns back into equal scans (bit for bit).

    Framed raw arrays rather than an ``.npz``: writing a zip archive cost more than parsing the
    request (it ran for every batch, on the event loop for small bodies).
    """
    parts = [_parts(scan) for scan in scans]
    header = json.dumps({"scans": [
        {"kind": kind, "scalars": int(scalars.size), "dtype": values.dtype.str, "shape": list(values.shape),
         **({} if scan.stamp_ns is None else {"stamp_ns": scan.stamp_ns})}
        for scan, (kind, scalars, values) in zip(scans, parts, strict=True)
    ]}).encode()
    chunks = [_MAGIC, _HEADER_LENGTH.pack(len(header)), header]
    for _, scalars, values in parts:
        chunks.append(scalars.tobytes())
        chunks.append(np.ascontiguousarray(values).tobytes())
    return b"".join(chunks)


def _scan(kind: str, scalars: list[float], values: np.ndarray, stamp_ns: int | None = None) -> Scan:
    if kind == "laser":
        x, y, theta, angle_min, increment, range_min, range_max, reg = scalars
        return LaserScan(pose=(x, y, theta), angle_min=angle_min, angle_increment=increment, ranges=values,
                         range_min=range_min, range_max=range_max, registration_sigma=reg,
                         max_rays=max(values.size, 1), stamp_ns=stamp_ns)
    *pose, range_max, reg = scalars
    if kind == "sensor_cloud" and len(pose) == 7:
        return PointCloud.from_sensor_frame(values, pose[:3], pose[3:], range_max, reg, stamp_ns,
                                            max_rays=max(values.shape[0], 1))
    if kind == "sensor_cloud":
        return PointCloud.from_planar_sensor_frame(values, (pose[0], pose[1], pose[2]), range_max, reg, stamp_ns,
                                                   max_rays=max(values.shape[0], 1))
    return PointCloud(points=values, origin=tuple(pose), range_max=range_max, registration_sigma=reg,
                      max_rays=max(values.shape[0], 1), stamp_ns=stamp_ns)


class CorruptBatch(ValueError):
    """A stored batch whose bytes do not decode (the message says where)."""


#: laser: pose, angles, ranges, sigma; cloud (map-frame points): origin (2 or 3), max, sigma; sensor_cloud (sensor-frame
#: points): pose (x, y, theta, or x, y, z, qx, qy, qz, qw), max, sigma
_SCALARS = {"laser": (8,), "cloud": (4, 5), "sensor_cloud": (5, 9)}


def decode(payload: bytes) -> Batch:
    """The batch of an :func:`encode` or :func:`encode_prior` blob, or the scans of a batch stored as ``.npz`` by an
    earlier version.

    Raises :class:`CorruptBatch` for bytes that are not such a blob, never reading past them.
    """
    return _guarded(_decode_any, payload)


def _decode_any(payload: bytes) -> Batch:
    if payload.startswith(_PRIOR_MAGIC):
        return _decode_prior(payload)
    if payload.startswith(_EDIT_MAGIC):
        return _decode_edit(payload)
    if not payload.startswith(_MAGIC):
        return _decode_npz(payload)
    return _decode_framed(payload)


_T = TypeVar("_T")


def _guarded(read: Callable[[bytes], _T], payload: bytes) -> _T:
    try:
        return read(payload)
    except CorruptBatch:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure to decode is corruption, named as such
        raise CorruptBatch(f"stored batch does not decode: {type(exc).__name__}: {exc}") from exc


#: How a stored scan takes a pose (``PoseTable.kinds``): in the plane (a LaserScan, a 2-D cloud: ``(x, y, theta)``),
#: whole (a 3-D cloud stored as taken: ``(x, y, z, qx, qy, qz, qw)``), or not at all (a cloud stored in the map frame,
#: before clouds were stored as taken: its sensor origin alone).
PLANAR, FULL, FIXED = 0, 1, 2


@dataclass(frozen=True)
class PoseTable:
    """The poses of a batch record's scans, in order, their beams left undecoded: ``stamps_ns`` (int64, -1:
    unstamped), ``kinds`` (int8: ``PLANAR``, ``FULL``, ``FIXED``) and ``poses``, one :func:`encode_poses` row per scan
    (a ``FIXED`` scan's row: its origin, 2 or 3 values, then NaN)."""

    stamps_ns: np.ndarray
    kinds: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return len(self.kinds)


@dataclass(frozen=True)
class ScanPose:
    """Where and when a stored scan was taken, without its beams: a LaserScan's (or a 2-D cloud's) ``(x, y)`` and
    ``yaw``; a 3-D cloud's position and ``orientation`` ``(qx, qy, qz, qw)``; or, for a cloud stored in the map frame,
    its origin alone (no orientation: it cannot be re-posed); ``stamp_ns`` None: unstamped."""

    position: tuple[float, ...]
    yaw: float | None
    stamp_ns: int | None
    orientation: tuple[float, float, float, float] | None = None


def pose_table(payload: bytes, moved: bytes | None = None) -> PoseTable:
    """The poses of a batch record's scans (none for a prior or an edit), at the rows of ``moved`` where a correction
    gave it some (``StoredMap.poses``: a NaN row, and a ``FIXED`` scan, keep the pose stored), as :func:`with_poses`
    places them; its beams left undecoded.

    Raises :class:`CorruptBatch` as :func:`decode` does, and when ``moved`` does not hold one row per scan.
    """
    table = _guarded(_pose_table, payload)
    if moved is None:
        return table
    rows = decode_poses(moved)
    if len(rows) != len(table):
        raise CorruptBatch(f"stored poses hold {len(rows)} rows for a batch of {len(table)} scans")
    widths = np.where(table.kinds == PLANAR, 3, np.where(table.kinds == FULL, POSE_WIDTH, 0))
    within = np.arange(POSE_WIDTH) < widths[:, None]
    taken = (widths > 0) & ~(np.isnan(rows) & within).any(axis=1)
    poses = table.poses.copy()
    poses[taken] = np.where(within[taken], rows[taken], np.nan)
    return PoseTable(table.stamps_ns, table.kinds, poses)


def _pose_table(payload: bytes) -> PoseTable:
    if payload.startswith(_MAGIC):
        scans = [(str(item["kind"]), int(item["scalars"]), at, item.get("stamp_ns")) for item, at, _ in _layout(payload)]
        scalars = [struct.unpack_from(f"<{count}d", payload, at) for _, count, at, _ in scans]
        kinds, stamps = [kind for kind, *_ in scans], [stamp for *_, stamp in scans]
    else:
        batch = _decode_any(payload)
        if not isinstance(batch, list):
            return PoseTable(np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros((0, POSE_WIDTH)))
        parts = [_parts(scan) for scan in batch]
        kinds, scalars, stamps = [kind for kind, *_ in parts], [p[1].tolist() for p in parts], [s.stamp_ns for s in batch]
    poses = np.full((len(kinds), POSE_WIDTH), np.nan)
    codes = np.empty(len(kinds), np.int8)
    for i, (kind, values) in enumerate(zip(kinds, scalars, strict=True)):
        # a laser's pose, a sensor cloud's ((x, y, yaw) or the whole pose), a cloud's origin: then its other scalars
        width = 3 if kind == "laser" else len(values) - 2
        codes[i] = FIXED if kind == "cloud" else PLANAR if width == 3 else FULL
        poses[i, :width] = values[:width]
    return PoseTable(np.array([-1 if s is None else s for s in stamps], dtype=np.int64), codes, poses)


def scan_poses(payload: bytes, moved: bytes | None = None) -> list[ScanPose]:
    """:func:`pose_table`'s poses one by one."""
    table = pose_table(payload, moved)
    out = []
    for stamp, kind, row in zip(table.stamps_ns.tolist(), table.kinds.tolist(), table.poses.tolist(), strict=True):
        at = None if stamp < 0 else stamp
        if kind == PLANAR:
            out.append(ScanPose((row[0], row[1]), row[2], at))
        elif kind == FULL:
            out.append(ScanPose((row[0], row[1], row[2]), None, at, (row[3], row[4], row[5], row[6])))
        else:
            out.append(ScanPose(tuple(v for v in row if not math.isnan(v)), None, at))
    return out


def decode_scans(payload: bytes) -> list[Scan]:
    """The scans of a scan batch's blob (``decode``); ``CorruptBatch`` for a prior's."""
    batch = decode(payload)
    if not isinstance(batch, list):
        raise CorruptBatch(f"stored batch is a {type(batch).__name__.lower()}, not scans")
    return batch


def encode_prior(prior: Prior) -> bytes:
    """A prior as bytes that :func:`decode` turns back into an equal one."""
    levels = np.ascontiguousarray(prior.levels, dtype=np.int8)
    header = json.dumps({"shape": list(levels.shape)}).encode()
    return b"".join([_PRIOR_MAGIC, _HEADER_LENGTH.pack(len(header)), header, zlib.compress(levels.tobytes(), 6)])


def encode_edit(edit: Edit) -> bytes:
    """An edit as bytes that :func:`decode` turns back into an equal one."""
    if isinstance(edit, Clear):
        body = {"op": "clear", "low": list(edit.low), "high": list(edit.high)}
    elif isinstance(edit, Reposed):
        body = {"op": "reposed", "correction": edit.correction, "through": edit.through, "scans": edit.scans}
    else:
        body = {"op": "forget_beyond", "metres": edit.metres}
    return _EDIT_MAGIC + json.dumps(body).encode()


def _decode_edit(payload: bytes) -> Edit:
    body = json.loads(payload[len(_EDIT_MAGIC):])
    if body.get("op") == "clear":
        low, high = tuple(float(v) for v in body["low"]), tuple(float(v) for v in body["high"])
        if len(low) not in (2, 3) or len(high) != len(low):
            raise CorruptBatch(f"stored clear has malformed corners {body!r}")
        return Clear(low, high)
    if body.get("op") == "reposed":
        return Reposed(str(body["correction"]), int(body["through"]), int(body["scans"]))
    if body.get("op") == "forget_beyond":
        metres = body["metres"]
        return SetForget(None if metres is None else float(metres))
    raise CorruptBatch(f"stored edit is of no known kind: {body!r}")


def _decode_prior(payload: bytes) -> Prior:
    offset = len(_PRIOR_MAGIC)
    (length,) = _HEADER_LENGTH.unpack_from(payload, offset)
    offset += _HEADER_LENGTH.size
    if offset + length > len(payload):
        raise CorruptBatch("stored prior is truncated inside its header")
    shape = tuple(int(n) for n in json.loads(payload[offset:offset + length])["shape"])
    if len(shape) not in (2, 3) or any(n < 1 for n in shape):
        raise CorruptBatch(f"stored prior has a malformed shape {shape}")
    size = math.prod(shape)
    inflate = zlib.decompressobj()
    raw = inflate.decompress(payload[offset + length:], size + 1)  # never more than the shape holds
    if len(raw) != size or not inflate.eof or inflate.unused_data:
        raise CorruptBatch(f"stored prior does not hold the {size} levels of its shape {shape}")
    return Prior(levels=np.frombuffer(raw, dtype=np.int8).reshape(shape))


def _take(payload: bytes, offset: int, dtype: np.dtype, count: int) -> np.ndarray:
    if count < 0 or offset + count * dtype.itemsize > len(payload):
        raise CorruptBatch(f"stored batch is truncated or its header is wrong ({count} values at byte {offset})")
    return np.frombuffer(payload, dtype=dtype, count=count, offset=offset)


def _frames(payload: bytes) -> Iterator[tuple[dict[str, Any], np.ndarray, np.ndarray]]:
    """Each scan of a framed record: its header entry, its scalars and its values (views of ``payload``, as stored),
    bounds-checked."""
    for item, scalars_at, values_at in _layout(payload):
        count, shape = int(item["scalars"]), tuple(int(n) for n in item["shape"])
        scalars = _take(payload, scalars_at, np.dtype("<f8"), count)
        yield item, scalars, _take(payload, values_at, _VALUE_DTYPES[item["dtype"]], math.prod(shape)).reshape(shape)


def _layout(payload: bytes) -> list[tuple[dict[str, Any], int, int]]:
    """Each scan of a framed record: its header entry and the byte offsets of its scalars and of its values, checked
    against the record's length."""
    offset = len(_MAGIC)
    (length,) = _HEADER_LENGTH.unpack_from(payload, offset)
    offset += _HEADER_LENGTH.size
    if offset + length > len(payload):
        raise CorruptBatch("stored batch is truncated inside its header")
    header = json.loads(payload[offset:offset + length])
    offset += length
    layout = []
    for item in header["scans"]:
        kind, count, shape = str(item["kind"]), int(item["scalars"]), tuple(int(n) for n in item["shape"])
        if count not in _SCALARS.get(kind, ()) or any(n < 0 for n in shape) or len(shape) != (1 if kind == "laser" else 2):
            raise CorruptBatch(f"stored batch has a malformed scan header: {item!r}")
        stamp = item.get("stamp_ns")
        if stamp is not None and (isinstance(stamp, bool) or not isinstance(stamp, int) or stamp < 0):
            raise CorruptBatch(f"stored batch has a malformed stamp: {item!r}")
        if item["dtype"] not in _VALUE_DTYPES:
            raise CorruptBatch(f"stored batch has a malformed scan header: {item!r}")
        scalars_at = offset
        offset += count * 8
        values_at = offset
        offset += math.prod(shape) * _VALUE_DTYPES[item["dtype"]].itemsize
        if offset > len(payload):
            raise CorruptBatch(f"stored batch is truncated or its header is wrong ({item!r} ends at byte {offset})")
        layout.append((item, scalars_at, values_at))
    if offset != len(payload):
        raise CorruptBatch(f"stored batch has {len(payload) - offset} bytes after its last scan")
    return layout


#: A batch's scans' current poses, where a corrected trajectory moved them: one row of ``POSE_WIDTH`` little-endian
#: float64 per scan of the batch, in order: ``(x, y, theta)`` then NaN for a LaserScan or a 2-D cloud, ``(x, y, z,
#: qx, qy, qz, qw)`` for a 3-D cloud; a NaN row keeps the scan's own pose.
POSE_DTYPE = np.dtype("<f8")
POSE_WIDTH = 7


def encode_poses(poses: np.ndarray) -> bytes:
    """A batch's scans' poses (``(n, POSE_WIDTH)`` float64, NaN rows: kept as stored) as a batch row's ``poses``."""
    return np.ascontiguousarray(poses, dtype=POSE_DTYPE).tobytes()


def decode_poses(data: bytes) -> np.ndarray:
    """The ``(n, POSE_WIDTH)`` poses of :func:`encode_poses`."""
    if len(data) % (POSE_WIDTH * POSE_DTYPE.itemsize):
        raise CorruptBatch(f"stored poses are {len(data)} bytes, not rows of {POSE_WIDTH} float64")
    return np.frombuffer(data, dtype=POSE_DTYPE).reshape(-1, POSE_WIDTH)


def with_poses(payload: bytes, poses: bytes) -> bytes:
    """``payload`` with its scans at the poses of ``poses`` (:func:`encode_poses`; NaN rows, and clouds stored in the map
    frame, keep theirs), everything else as stored, bit for bit: what the batch replays as once a correction moved it.

    Raises :class:`CorruptBatch` when ``poses`` does not hold one row per scan.
    """
    return _guarded(lambda data: _with_poses(data, decode_poses(poses)), payload)


def moved(batches: Sequence[tuple[int, bytes]], poses: Mapping[int, bytes]) -> list[tuple[int, bytes]]:
    """A map's stored (version, payload) batches as they replay: each at the poses a correction gave it, if any
    (``StoredMap.poses``; :func:`with_poses`)."""
    if not poses:
        return list(batches)
    return [(version, payload if version not in poses else with_poses(payload, poses[version]))
            for version, payload in batches]


def _with_poses(payload: bytes, poses: np.ndarray) -> bytes:
    if not payload.startswith(_MAGIC):  # a batch stored before the framed record: written again as one
        batch = _decode_any(payload)
        if not isinstance(batch, list):
            raise CorruptBatch(f"stored poses for a {type(batch).__name__.lower()}, which has no scans")
        return _with_poses(encode(batch), poses)
    layout = _layout(payload)
    if len(layout) != len(poses):
        raise CorruptBatch(f"stored poses hold {len(poses)} rows for a batch of {len(layout)} scans")
    patched = bytearray(payload)
    for (item, scalars_at, _), pose in zip(layout, poses, strict=True):
        width = int(item["scalars"]) - 2 if item["kind"] == "sensor_cloud" else 3 if item["kind"] == "laser" else 0
        if width and not np.isnan(pose[:width]).any():
            patched[scalars_at:scalars_at + width * POSE_DTYPE.itemsize] = pose[:width].astype(POSE_DTYPE).tobytes()
    return bytes(patched)


def _decode_framed(payload: bytes) -> list[Scan]:
    return [_scan(str(item["kind"]), scalars.tolist(), values.astype(np.float64), item.get("stamp_ns"))
            for item, scalars, values in _frames(payload)]


def _decode_npz(payload: bytes) -> list[Scan]:
    with np.load(io.BytesIO(payload), allow_pickle=False) as archive:
        kinds = [str(k) for k in archive["kinds"]]
        return [_scan(kind, archive[f"s{i}_scalars"].tolist(), archive[f"s{i}_values"].astype(np.float64))
                for i, kind in enumerate(kinds)]
