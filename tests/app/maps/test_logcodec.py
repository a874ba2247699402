"""The batch log's prior record (a saved map's cells): encoded and decoded bit for bit, corruption named, never
inflated past its shape; scan batches decode as before beside it (``tests/app/maps/test_writepath.py``)."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest

from app.maps import logcodec
from app.maps.logcodec import Prior
from fuzzyocc import LaserScan
from fuzzyocc.maps import PRIOR_UNSEEN


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
