"""A snapshot's record: a fuzzy and a Bayes map's arrays round trip bit for bit and restore the same map; snapshots
stored as ``.npz`` before still decode; a damaged record is named as such, never inflated past its header's sizes."""

from __future__ import annotations

import io
import json
import struct

import numpy as np
import pytest
import zstandard

from app.maps import snapshotcodec
from app.maps.snapshotcodec import CorruptSnapshot
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan

SPEC = GridSpec(origin=(-4.0, -4.0), size=(8.0, 8.0), resolution=0.05)


def _scans() -> list[LaserScan]:
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    ranges = 3.0 + 0.5 * np.sin(3 * angles)
    ranges[::17] = np.inf  # no-returns
    return [LaserScan(pose=(0.1 * k, 0.0, 0.2 * k), angle_min=-np.pi, angle_increment=2 * np.pi / 360,
                      ranges=ranges, range_min=0.05, range_max=3.8) for k in range(3)]


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(
        np.asarray(a[k]).dtype == b[k].dtype and np.asarray(a[k]).shape == b[k].shape
        and np.asarray(a[k]).tobytes() == b[k].tobytes() for k in a)


@pytest.mark.parametrize("model", [FuzzyMap, BayesMap])
def test_a_maps_snapshot_restores_the_same_map(model: type[FuzzyMap] | type[BayesMap]) -> None:
    built = model(SPEC)
    built.integrate_batch(_scans())
    arrays = built.snapshot_arrays()

    payload = snapshotcodec.encode(arrays)
    back = snapshotcodec.decode(payload)

    assert payload.startswith(b"FRS\x01") and _same(arrays, back)
    restored = model.from_arrays(SPEC, None, back)
    assert restored.risk().tobytes() == built.risk().tobytes()
    assert np.array_equal(restored.observed(), built.observed())


@pytest.mark.parametrize("model", [FuzzyMap, BayesMap])
def test_a_maps_arrays_encoded_in_place_on_two_threads_give_the_same_snapshot(
        model: type[FuzzyMap] | type[BayesMap]) -> None:
    built = model(SPEC)
    built.integrate_batch(_scans())
    copies = built.snapshot_arrays()

    views = built.snapshot_arrays(copy=False)
    back = snapshotcodec.decode(snapshotcodec.encode(views, threads=2))

    assert _same(copies, back)
    assert not any(np.shares_memory(copies[k], views[k]) for k in copies)
    assert model.from_arrays(SPEC, None, back).risk().tobytes() == built.risk().tobytes()


def test_a_snapshot_stored_as_npz_before_still_decodes() -> None:
    built = FuzzyMap(SPEC)
    built.integrate_batch(_scans())
    arrays = built.snapshot_arrays()
    old = io.BytesIO()
    np.savez_compressed(old, **arrays)  # an earlier version's snapshot: a zip of .npy members

    assert _same(arrays, snapshotcodec.decode(old.getvalue()))


def _record(header: object, frame: bytes) -> bytes:
    text = json.dumps(header).encode()
    return b"FRS\x01" + struct.pack("<I", len(text)) + text + frame


_PAYLOAD = snapshotcodec.encode({"slabs": np.arange(4096, dtype=np.uint8)})
_FRAME = zstandard.ZstdCompressor().compress(bytes(4096))  # states its size: 4096


@pytest.mark.parametrize("record", [
    pytest.param(_PAYLOAD[:-5], id="truncated frame"),
    pytest.param(_PAYLOAD[:12], id="truncated header"),
    pytest.param(_PAYLOAD[:8] + b"}" + _PAYLOAD[9:], id="header not JSON"),
    pytest.param(_record({"arrays": [["slabs", "|u1", [8192]]]}, _FRAME), id="header naming more than the frame"),
    pytest.param(_record({"arrays": [["slabs", "|u1", [16]]]}, _FRAME), id="header naming less than the frame"),
    pytest.param(_record({"arrays": [["slabs", "|O", [1]]]}, _FRAME), id="objects"),
])
def test_a_damaged_snapshot_is_named_corrupt(record: bytes) -> None:
    with pytest.raises(CorruptSnapshot, match="stored snapshot"):
        snapshotcodec.decode(record)


def test_arrays_of_python_objects_are_refused() -> None:
    with pytest.raises(ValueError, match="no Python objects"):
        snapshotcodec.encode({"things": np.array([object()])})
