"""A batch cast ahead of its fusion (``prepare_batch``, the map left as it is) fuses into the map a plain
``integrate_batch`` gives, bit for bit, whether the map changed in between or not."""

import math

import numpy as np
import pytest

from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan, LatticeSpec, PointCloud, SensorModel


def _scans(rng: np.random.Generator, n: int, ndim: int) -> list[LaserScan] | list[PointCloud]:
    if ndim == 3:
        return [PointCloud(points=rng.uniform((0.2, 0.2, 0.1), (5.8, 5.8, 2.9), (2000, 3)),
                           origin=(3.0 + 0.2 * k, 3.0, 1.5), range_max=4.0) for k in range(n)]
    scans = []
    for k in range(n):
        ranges = rng.uniform(0.5, 5.5, 360)
        ranges[rng.uniform(size=360) < 0.1] = math.inf
        scans.append(LaserScan(pose=(3.0 + 0.1 * k, 3.0 - 0.05 * k, 0.3 * k), angle_min=-math.pi,
                               angle_increment=2 * math.pi / 360, ranges=ranges, range_min=0.1, range_max=5.0))
    return scans


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]) for k in a)


CASES = [(FuzzyMap, "growing", 2), (FuzzyMap, "growing", 3), (FuzzyMap, "box", 2), (FuzzyMap, "box", 3),
         (BayesMap, "box", 2)]


def _spec(extent: str, ndim: int) -> GridSpec | LatticeSpec:
    res = 0.05 if ndim == 2 else 0.1
    return GridSpec(origin=(0.0,) * ndim, size=(6.0, 6.0, 3.0)[:ndim], resolution=res) if extent == "box" \
        else LatticeSpec(ndim, res)


@pytest.mark.parametrize(("model", "extent", "ndim"), CASES)
def test_a_batch_cast_ahead_fuses_into_the_map_a_plain_fusion_gives(model, extent, ndim) -> None:
    batches = [_scans(np.random.default_rng(k), 2, ndim) for k in range(4)]
    plain, ahead = model(_spec(extent, ndim), SensorModel()), model(_spec(extent, ndim), SensorModel())
    for batch in batches:
        expected = plain.integrate_batch(batch)
        before = ahead.to_arrays()
        prepared = ahead.prepare_batch(batch)
        assert prepared is not None
        assert _same(before, ahead.to_arrays())  # casting ahead leaves the map as it was: readers may read it
        assert ahead.integrate_batch(batch, prepared) == expected
    assert _same(plain.to_arrays(), ahead.to_arrays())


@pytest.mark.parametrize(("model", "extent", "ndim"), CASES)
def test_a_cast_made_before_the_map_changed_is_made_again(model, extent, ndim) -> None:
    first, second = (_scans(np.random.default_rng(k), 2, ndim) for k in (1, 2))
    plain, ahead = model(_spec(extent, ndim), SensorModel()), model(_spec(extent, ndim), SensorModel())
    plain.integrate_batch(first)
    plain.integrate_batch(second)
    stale = ahead.prepare_batch(second)  # cast before the first batch's blocks were entered
    ahead.integrate_batch(first)
    ahead.integrate_batch(second, stale)
    assert _same(plain.to_arrays(), ahead.to_arrays())
    if extent == "growing":  # a forgetting map drops blocks: a cast made before is made again too
        plain.forget_beyond = ahead.forget_beyond = 1.0
        third = _scans(np.random.default_rng(3), 1, ndim)
        again = ahead.prepare_batch(third)
        ahead.integrate_batch(second)
        plain.integrate_batch(second)
        ahead.integrate_batch(third, again)
        plain.integrate_batch(third)
        assert _same(plain.to_arrays(), ahead.to_arrays())


def test_a_cast_of_other_scans_is_refused() -> None:
    m = FuzzyMap(LatticeSpec(2, 0.05), SensorModel())
    one, other = _scans(np.random.default_rng(1), 1, 2), _scans(np.random.default_rng(2), 1, 2)
    prepared = m.prepare_batch(one)
    with pytest.raises(ValueError, match="other scans"):
        m.integrate_batch(other, prepared)
    assert m.scans_fused == 0


def test_a_cast_does_not_fit_an_index_that_dropped_a_block_even_back_at_its_count() -> None:
    from fuzzyocc._block_table import BlockIndex
    from fuzzyocc.raycast import CastResult, _enter, fits

    index = BlockIndex()
    index.reserve(4)
    index.n = _enter(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], np.int32), index.keys, index.slots, index.coords,
                     index.n)
    empty = np.zeros(0, np.int64)
    cast = CastResult(empty, np.zeros(0, np.float32), np.zeros(1, np.int64), empty, np.zeros((0, 3), np.int32),
                      (index.n, index.dropped))
    assert fits(index, cast)
    index.drop(0)  # the block at (2, 0, 0) moves to slot 0: slot 2 is another block's from here
    index.n = _enter(np.array([[5, 0, 0]], np.int32), index.keys, index.slots, index.coords, index.n)
    assert index.n == cast.index_at[0] and not fits(index, cast)
