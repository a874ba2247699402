"""A corrected trajectory applied to a map's history: the new pose of each stored scan it covers, and back.

``plan`` reads the stamps and poses of the history's scans (``logcodec.pose_table``, beams left undecoded) and gives
each scan whose stamp lies in the trajectory's ``[first, last]`` its pose there (``Trajectory.poses_at``, as tf2
interpolates): a LaserScan or a 2-D cloud as one posted at that pose would be placed
(``fuzzyocc.trajectory.laser_poses``), a 3-D cloud the whole pose. Scans outside
the range, unstamped ones and every scan stored after the map's version at the request keep theirs. The result is
stored with the correction (``encode`` / ``decode``) until the map has been rebuilt at it; the rebuild replays the
history with these poses (``apply``).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from app.errors import Invalid, TooLarge
from app.maps import logcodec
from app.ros.path_in import corrected_path
from app.schemas import CorrectedPath
from app.schemas.common import ns_of_ros_time
from app.storage import StoredMap
from fuzzyocc.trajectory import Trajectory, laser_poses

#: ``Trajectory``'s names of its fields, and where they are in a ``CorrectedPath`` body (errors name the body's).
_FIELDS = {"stamps_ns[": "poses[{}].header.stamp", "positions[": "poses[{}].pose.position",
           "quaternions[": "poses[{}].pose.orientation"}


class NothingToCorrect(ValueError):
    """No stored scan has a stamp in the trajectory's range (the message says what the map's stamps span)."""


class CannotRepose(ValueError):
    """A stored scan in the trajectory's range cannot take a new pose (a point cloud; the message says which)."""


@dataclass(frozen=True)
class Correction:
    """The new poses of a map's history: ``moves`` maps a batch's version to one ``logcodec.encode_poses`` row per scan
    of it (NaN rows: kept as they are), for the batches up to ``through`` (the map's version at the request) that have a
    scan in the trajectory's range; ``scans`` counts the scans moved."""

    through: int
    moves: dict[int, np.ndarray]
    scans: int


#: A sensor's fixed pose on a robot: position (metres) and quaternion ``[x, y, z, w]``.
SensorOffset = tuple[tuple[float, float, float], tuple[float, float, float, float]]


def read_trajectory(body: bytes, frame_id: str, offset: SensorOffset | None, max_poses: int) -> Trajectory:
    """The sensor's trajectory of a ``PUT /maps/{name}/trajectory`` JSON body (``corrected_path``, then
    ``sensor_trajectory``): run in a parse thread, or for a large body in the parse process. ``TooLarge`` past
    ``max_poses`` (``FUZZYRISK_MAX_TRAJECTORY_POSES``)."""
    path = corrected_path(body)
    if len(path.poses) > max_poses:
        raise TooLarge(f"poses: {len(path.poses):,} poses, more than FUZZYRISK_MAX_TRAJECTORY_POSES ({max_poses:,})")
    return sensor_trajectory(path, frame_id, offset)


def sensor_trajectory(path: CorrectedPath, frame_id: str, offset: SensorOffset | None) -> Trajectory:
    """The sensor's trajectory of a ``PUT /maps/{name}/trajectory`` body: its poses, or with ``offset`` (the sensor's
    fixed pose on the robot, a static TF ``base_link -> laser``: position and quaternion) each pose composed with it.

    ``Invalid`` naming the body's field: another frame than the map's, stamps that do not strictly increase, a
    quaternion that is not a unit one.
    """
    if path.header.frame_id != frame_id:
        raise Invalid(f"header.frame_id is {path.header.frame_id!r}: a corrected trajectory is given in the map's frame, "
                      f"{frame_id!r}")
    stamps = np.array([ns_of_ros_time(p.header.stamp) for p in path.poses], dtype=np.int64)
    positions = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in path.poses])
    quaternions = np.array([[p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w]
                            for p in path.poses])
    try:
        trajectory = Trajectory(stamps, positions, quaternions)
        if offset is not None:
            trajectory = trajectory.with_offset(*offset)
    except ValueError as exc:
        message = str(exc)
        for name, field in _FIELDS.items():
            if message.startswith(name):
                index, _, rest = message[len(name):].partition("]")
                message = field.format(index) + rest
                break
        raise Invalid(message.replace("stamps_ns[", "poses[").replace("offset ", "offset_")) from None
    return trajectory


def plan(history: StoredMap, trajectory: Trajectory, through: int) -> Correction:
    """The correction ``trajectory`` (the sensor's, offsets applied) makes to the history's batches up to ``through``.

    Raises ``NothingToCorrect`` (no stamped scan in range), ``CannotRepose`` (a cloud stored in the map frame in range),
    ``fuzzyocc.tf.NotLevel`` (a pose in range tilts the scanner off level) and ``logcodec.CorruptBatch``.
    """
    versions: list[int] = []
    tables: list[logcodec.PoseTable] = []
    for version, payload in history.batches:
        if version > through:
            break
        table = logcodec.pose_table(payload, history.poses.get(version))
        if len(table):
            versions.append(version)
            tables.append(table)
    if not tables:
        raise _nothing(trajectory, np.zeros(0, np.int64))
    at = np.concatenate([t.stamps_ns for t in tables])
    kind = np.concatenate([t.kinds for t in tables])
    yaws = np.concatenate([t.poses[:, 2] for t in tables])  # a planar pose's heading
    counts = [len(t) for t in tables]
    stamped = at >= 0
    inside = np.zeros(at.size, dtype=bool)
    positions = np.full((at.size, 3), np.nan)
    quaternions = np.full((at.size, 4), np.nan)
    if stamped.any():
        found = trajectory.poses_at(at[stamped])
        inside[stamped] = found.inside
        positions[stamped], quaternions[stamped] = found.positions, found.quaternions
    if not inside.any():
        raise _nothing(trajectory, at[stamped])
    fixed = np.flatnonzero(inside & (kind == logcodec.FIXED))
    if fixed.size:
        raise CannotRepose(f"{fixed.size} stored point clouds have stamps in the trajectory's range (the first at "
                           f"{int(at[fixed[0]])} ns) and were stored in the map frame, without the pose they were "
                           "placed at (before clouds were stored as taken): they cannot be re-posed; correct a "
                           "range after them")
    new = np.full((at.size, logcodec.POSE_WIDTH), np.nan)
    planar, full = inside & (kind == logcodec.PLANAR), inside & (kind == logcodec.FULL)
    new[planar, :3] = laser_poses(positions[planar], quaternions[planar], yaws[planar])
    new[full] = np.column_stack([positions[full], quaternions[full]])  # a 3-D sensor takes the pose as it is
    moves: dict[int, np.ndarray] = {}
    offset = 0
    for version, count in zip(versions, counts, strict=True):
        rows = new[offset:offset + count]
        if not np.isnan(rows).all():
            moves[version] = rows
        offset += count
    return Correction(through, moves, int(inside.sum()))


def _nothing(trajectory: Trajectory, stamps: np.ndarray) -> NothingToCorrect:
    span = f"scans stamped {int(stamps.min())} to {int(stamps.max())} ns" if stamps.size else "no stamped scan"
    return NothingToCorrect(f"no stored scan has a stamp in the trajectory's range ({int(trajectory.stamps_ns[0])} to "
                            f"{int(trajectory.stamps_ns[-1])} ns); the map's history holds {span}")


def apply(history: StoredMap, correction: Correction) -> StoredMap:
    """``history`` with the correction's poses in place of those its batches replayed at (``StoredMap.poses``): a
    moved batch takes every row of the correction (a scan it leaves, NaN, keeps the pose it had before)."""
    for version, rows in correction.moves.items():
        before = history.poses.get(version)
        if before is not None:
            rows = np.where(np.isnan(rows), logcodec.decode_poses(before), rows)
        history.poses[version] = logcodec.encode_poses(rows)
    return history


def encode(correction: Correction) -> bytes:
    """A correction as the bytes stored with it until the rebuild is done."""
    versions = np.fromiter(correction.moves, dtype=np.int64, count=len(correction.moves))
    counts = np.array([len(rows) for rows in correction.moves.values()], dtype=np.int64)
    rows = np.concatenate(list(correction.moves.values())) if correction.moves else np.zeros((0, logcodec.POSE_WIDTH))
    out = io.BytesIO()
    np.savez(out, allow_pickle=False, through=np.int64(correction.through), scans=np.int64(correction.scans),
             versions=versions, counts=counts, poses=rows.astype("<f8"))
    return out.getvalue()


def decode(payload: bytes) -> Correction:
    """The correction of :func:`encode`'s bytes."""
    with np.load(io.BytesIO(payload), allow_pickle=False) as archive:
        versions, counts, rows = archive["versions"], archive["counts"], archive["poses"]
        through, scans = int(archive["through"]), int(archive["scans"])
    ends = np.cumsum(counts)
    moves = {int(v): rows[end - n:end] for v, n, end in zip(versions, counts, ends, strict=True)}
    return Correction(through, moves, scans)
