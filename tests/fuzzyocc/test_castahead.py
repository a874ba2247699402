"""Batches fused through ``CastAhead`` (the next batch cast in a second thread while one fuses) make the map a plain
``integrate_batch`` of each in turn makes, bit for bit; a batch that is not the one named next, or that cannot be
fused, is handled as a plain fusion handles it."""

import dataclasses
import threading

import numpy as np
import pytest

from fuzzyocc import FuzzyMap, LatticeSpec, PointCloud, SensorModel
from fuzzyocc.castahead import CastAhead
from tests.fuzzyocc.test_prepared import CASES, _same, _scans, _spec


def _ahead_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("cast-ahead")]


@pytest.mark.parametrize(("model", "extent", "ndim"), CASES)
def test_batches_cast_ahead_make_the_map_a_plain_fusion_makes(model, extent, ndim) -> None:
    batches = [_scans(np.random.default_rng(k), 3, ndim) for k in range(6)]
    plain, ahead = model(_spec(extent, ndim), SensorModel()), model(_spec(extent, ndim), SensorModel())
    with CastAhead(ahead) as fuse:
        for k, batch in enumerate(batches):
            expected = plain.integrate_batch(batch)
            assert fuse.integrate(batch, batches[k + 1] if k + 1 < len(batches) else None) == expected
    assert _same(plain.to_arrays(), ahead.to_arrays())
    assert not _ahead_threads()  # leaving ends its thread


def test_batches_cast_in_several_chunks_fuse_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    # a bound of a few scans' cast entries a chunk: each batch of 5 is cast in several chunks, each chunk's successor
    # (in the batch, or the next batch's first) cast while it fuses
    monkeypatch.setattr("fuzzyocc.maps.CAST_CHUNK_ENTRIES", 60_000)
    batches = [_scans(np.random.default_rng(k), 5, 2) for k in range(4)]
    plain, ahead = FuzzyMap(LatticeSpec(2, 0.05), SensorModel()), FuzzyMap(LatticeSpec(2, 0.05), SensorModel())
    assert len(ahead.chunked(batches[0])) > 2
    with CastAhead(ahead) as fuse:
        for k, batch in enumerate(batches):
            expected = plain.integrate_batch(batch)
            assert fuse.integrate(batch, batches[k + 1] if k + 1 < len(batches) else None) == expected
    assert _same(plain.to_arrays(), ahead.to_arrays())


def test_sweeps_whose_cast_splits_between_threads_fuse_the_same() -> None:
    # 2 x 12,000 rays a batch: the cast made ahead splits its walks in the pool while the fusion beside it splits
    # its writes there too
    rng = np.random.default_rng(7)
    batches = [[PointCloud(points=rng.uniform((-8, -8, -1), (8, 8, 3), (12_000, 3)), origin=(0.5 * k, 0.0, 1.0),
                           range_max=10.0) for k in range(2)] for _ in range(4)]
    plain, ahead = FuzzyMap(LatticeSpec(3, 0.1), SensorModel()), FuzzyMap(LatticeSpec(3, 0.1), SensorModel())
    with CastAhead(ahead) as fuse:
        for k, batch in enumerate(batches):
            plain.integrate_batch(batch)
            fuse.integrate(batch, batches[k + 1] if k + 1 < len(batches) else None)
    assert _same(plain.to_arrays(), ahead.to_arrays())


def test_a_forgetting_map_and_a_batch_other_than_the_one_named_fuse_the_same() -> None:
    batches = [_scans(np.random.default_rng(k), 1, 2) for k in range(5)]
    plain, ahead = FuzzyMap(LatticeSpec(2, 0.05), SensorModel()), FuzzyMap(LatticeSpec(2, 0.05), SensorModel())
    plain.forget_beyond = ahead.forget_beyond = 1.5  # each fusion drops blocks: nothing may be cast beside it
    with CastAhead(ahead) as fuse:
        for k, batch in enumerate(batches):
            plain.integrate_batch(batch)
            fuse.integrate(batch, batches[k + 1] if k + 1 < len(batches) else None)
    assert _same(plain.to_arrays(), ahead.to_arrays())
    plain.forget_beyond = ahead.forget_beyond = None
    named, fused = _scans(np.random.default_rng(10), 2, 2), _scans(np.random.default_rng(11), 2, 2)
    with CastAhead(ahead) as fuse:
        fuse.integrate(batches[0], named)
        fuse.integrate(fused)  # not the batch named: its own cast, as a plain fusion makes it
    plain.integrate_batch(batches[0])
    plain.integrate_batch(fused)
    assert _same(plain.to_arrays(), ahead.to_arrays())


def test_a_bad_batch_cast_ahead_is_refused_as_a_plain_fusion_refuses_it() -> None:
    good = _scans(np.random.default_rng(1), 2, 2)
    bad = _scans(np.random.default_rng(2), 2, 2)
    bad[1] = dataclasses.replace(bad[1], pose=(2.0e9, 0.0, 0.0))  # beyond any local map frame
    m = FuzzyMap(LatticeSpec(2, 0.05), SensorModel())
    with CastAhead(m) as fuse:
        fuse.integrate(good, bad)
        before = m.to_arrays()
        with pytest.raises(ValueError, match=r"scans\[1\]"):
            fuse.integrate(bad)
        assert _same(before, m.to_arrays())
        assert m.scans_fused == 2


def test_leaving_while_a_cast_runs_waits_for_it() -> None:
    batches = [_scans(np.random.default_rng(k), 3, 3) for k in range(2)]
    m = FuzzyMap(LatticeSpec(3, 0.1), SensorModel())
    with pytest.raises(RuntimeError, match="stopped"):
        with CastAhead(m) as fuse:
            fuse.integrate(batches[0], batches[1])  # the second batch's cast is left running, or done, unused
            raise RuntimeError("stopped")  # a replay's progress callback stops it
    assert not _ahead_threads()
    assert m.scans_fused == 3
