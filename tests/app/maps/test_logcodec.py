"""The batch log's records: a prior (a saved map's cells) encoded and decoded bit for bit, corruption named, never
inflated past its shape; scans with their stamps round trip bit for bit, and records stored before stamps (framed
without them, ``.npz``) decode unstamped (more of scan batches: ``tests/app/maps/test_writepath.py``)."""

from __future__ import annotations

import json
import struct
import zlib
from typing import Any

import numpy as np
import pytest

from app.maps import logcodec
from app.maps.logcodec import Prior
from app.scans import Scan
from fuzzyocc import LaserScan, PointCloud
from fuzzyocc.maps import PRIOR_UNSEEN
from tests.app.maps.test_writepath import _legacy_npz


def _levels() -> np.ndarray:
    rng = np.random.default_rng(2)
    levels = rng.integers(-3, 4, size=(120, 80)).astype(np.int8)
    levels[:60] = PRIOR_UNSEEN  # a saved map is mostly long runs
    return levels


def test_a_prior_decodes_to_the_same_levels_and_takes_little_room() -> None:
    levels = _levels()
    payload = logcodec.encode_prior(Prior(levels))
    assert payload.startswith(b"FRP\x01") and len(payload) < levels.size // 2
    back = logcodec.decode(payload)
    assert isinstance(back, Prior)
    assert back.levels.dtype == np.int8 and back.levels.shape == levels.shape
    assert np.array_equal(back.levels, levels)


def test_scan_batches_and_priors_tell_themselves_apart() -> None:
    scan = LaserScan(pose=(0.0, 0.0, 0.0), angle_min=0.0, angle_increment=0.01, ranges=[1.0, 2.0], range_min=0.1,
                     range_max=8.0)
    scans = logcodec.encode([scan])
    assert isinstance(logcodec.decode(scans), list) and len(logcodec.decode_scans(scans)) == 1
    with pytest.raises(logcodec.CorruptBatch, match="a prior, not scans"):
        logcodec.decode_scans(logcodec.encode_prior(Prior(_levels())))


def _forged(shape: object, body: bytes) -> bytes:
    header = json.dumps({"shape": shape}).encode()
    return b"FRP\x01" + struct.pack("<I", len(header)) + header + body


def test_a_corrupt_prior_is_named_as_such_and_never_inflated_past_its_shape() -> None:
    payload = logcodec.encode_prior(Prior(_levels()))
    for cut in range(0, len(payload), 7):  # truncated anywhere
        with pytest.raises(logcodec.CorruptBatch):
            logcodec.decode(payload[:cut])
    with pytest.raises(logcodec.CorruptBatch):
        logcodec.decode(payload + b"\0")
    # a stream that would inflate to 100 MB under a header of 4 cells stops after 5 bytes
    with pytest.raises(logcodec.CorruptBatch, match="does not hold the 4 levels"):
        logcodec.decode(_forged([2, 2], zlib.compress(bytes(100 * 2**20))))
    for shape in ([-1, 4], [0, 3], [5], "x"):
        with pytest.raises(logcodec.CorruptBatch):
            logcodec.decode(_forged(shape, zlib.compress(bytes(4))))


# ---------------------------------------------------------------- stamps


def _stamped_batch() -> list[Scan]:
    rng = np.random.default_rng(4)
    laser = LaserScan(pose=(1.25, -3.5, 0.7), angle_min=-1.0, angle_increment=0.01, ranges=rng.uniform(0.5, 9.0, 201).astype(np.float32),
                      range_min=0.1, range_max=8.0, registration_sigma=0.02, stamp_ns=1_796_614_484_690_952_831)
    unstamped = LaserScan(pose=(0.0, 0.0, 0.0), angle_min=0.0, angle_increment=0.5, ranges=[1.0, np.inf, np.nan],
                          range_min=0.1, range_max=8.0)
    cloud = PointCloud(points=rng.normal(size=(50, 3)), origin=(0.5, 0.25, 1.5), range_max=20.0, stamp_ns=0)
    return [laser, unstamped, cloud]


def _fields(scan: Scan) -> tuple[object, ...]:
    values = scan.ranges if isinstance(scan, LaserScan) else scan.points
    where = scan.pose if isinstance(scan, LaserScan) else scan.origin
    return type(scan), where, values.tobytes(), values.shape, scan.registration_sigma, scan.stamp_ns


def test_stamps_round_trip_exactly_with_their_scans_bit_for_bit() -> None:
    batch = _stamped_batch()
    payload = logcodec.encode(batch)
    back = logcodec.decode_scans(payload)
    assert [_fields(s) for s in back] == [_fields(s) for s in batch]
    assert [s.stamp_ns for s in back] == [1_796_614_484_690_952_831, None, 0]
    assert logcodec.encode(back) == payload  # and back to the same bytes
    assert logcodec.scan_poses(payload) == [
        logcodec.ScanPose((1.25, -3.5), 0.7, 1_796_614_484_690_952_831), logcodec.ScanPose((0.0, 0.0), 0.0, None),
        logcodec.ScanPose((0.5, 0.25, 1.5), None, 0)]


def test_a_records_poses_at_a_stored_correction_are_those_it_replays_at() -> None:
    payload = logcodec.encode(_stamped_batch())
    rows = np.full((3, logcodec.POSE_WIDTH), np.nan)
    rows[1, :3] = (4.0, 5.0, -0.25)  # the unstamped LaserScan moved; the first kept (NaN); the cloud cannot move
    rows[2, :3] = (9.0, 9.0, 9.0)
    moved = logcodec.encode_poses(rows)
    table = logcodec.pose_table(payload, moved)
    assert table.kinds.tolist() == [logcodec.PLANAR, logcodec.PLANAR, logcodec.FIXED]
    assert table.stamps_ns.tolist() == [1_796_614_484_690_952_831, -1, 0]
    # the poses the record replays at (with_poses, then decoded), read without decoding the beams
    replayed = logcodec.decode_scans(logcodec.with_poses(payload, moved))
    assert logcodec.scan_poses(payload, moved) == logcodec.scan_poses(logcodec.with_poses(payload, moved))
    assert [p.position for p in logcodec.scan_poses(payload, moved)] == [
        replayed[0].pose[:2], replayed[1].pose[:2], replayed[2].origin]
    assert logcodec.scan_poses(payload, moved)[1] == logcodec.ScanPose((4.0, 5.0), -0.25, None)
    with pytest.raises(logcodec.CorruptBatch, match="2 rows for a batch of 3 scans"):
        logcodec.pose_table(payload, logcodec.encode_poses(rows[:2]))


def _header_of(payload: bytes) -> tuple[dict[str, Any], int]:
    (length,) = struct.unpack_from("<I", payload, 4)
    return json.loads(payload[8:8 + length]), 8 + length


def test_a_record_stored_before_stamps_decodes_unstamped() -> None:
    batch = _stamped_batch()
    payload = logcodec.encode(batch)
    header, body = _header_of(payload)
    for item in header["scans"]:
        item.pop("stamp_ns", None)
    old_header = json.dumps(header).encode()  # the header an earlier version wrote: no stamp_ns
    old = b"FRB\x01" + struct.pack("<I", len(old_header)) + old_header + payload[body:]
    back = logcodec.decode_scans(old)
    assert [s.stamp_ns for s in back] == [None, None, None]
    assert [_fields(s)[:-1] for s in back] == [_fields(s)[:-1] for s in batch]
    assert [p.stamp_ns for p in logcodec.scan_poses(old)] == [None, None, None]


def test_an_npz_record_of_an_earlier_version_decodes_unstamped() -> None:
    laser, _, cloud = _stamped_batch()
    old = _legacy_npz([laser, cloud])
    back = logcodec.decode_scans(old)
    assert [_fields(s)[:-1] for s in back] == [_fields(laser)[:-1], _fields(cloud)[:-1]]
    assert [s.stamp_ns for s in back] == [None, None]
    assert logcodec.scan_poses(old) == [logcodec.ScanPose((1.25, -3.5), 0.7, None),
                                        logcodec.ScanPose((0.5, 0.25, 1.5), None, None)]


@pytest.mark.parametrize("stamp", [-1, 1.5, "5", True])
def test_a_record_with_a_malformed_stamp_is_corrupt(stamp: object) -> None:
    payload = logcodec.encode(_stamped_batch())
    header, body = _header_of(payload)
    header["scans"][0]["stamp_ns"] = stamp
    forged_header = json.dumps(header).encode()
    forged = b"FRB\x01" + struct.pack("<I", len(forged_header)) + forged_header + payload[body:]
    for read in (logcodec.decode, logcodec.scan_poses):
        with pytest.raises(logcodec.CorruptBatch, match="stamp"):
            read(forged)


def test_the_poses_of_a_prior_or_an_edit_are_none() -> None:
    assert logcodec.scan_poses(logcodec.encode_prior(Prior(_levels()))) == []
    assert logcodec.scan_poses(logcodec.encode_edit(logcodec.SetForget(5.0))) == []
