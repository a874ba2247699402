"""Fusion split between threads gives the map one thread gives, bit for bit: the walks of a cast split a scan's rays,
the writes of a fusion split its blocks, and neither split shows in the map."""

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan, LatticeSpec, PointCloud, SensorModel, parallel


def _room_scans(rng: np.random.Generator, n: int) -> list[LaserScan]:
    scans = []
    for k in range(n):
        ranges = rng.uniform(0.5, 5.5, 720)
        ranges[rng.uniform(size=720) < 0.1] = math.inf  # no-returns
        ranges[rng.uniform(size=720) < 0.02] = math.nan  # skipped
        scans.append(LaserScan(pose=(3.0 + 0.1 * k, 3.0 - 0.05 * k, 0.3 * k), angle_min=-math.pi,
                               angle_increment=2 * math.pi / 720, ranges=ranges, range_min=0.1, range_max=5.0))
    return scans


def _clouds(rng: np.random.Generator, n: int) -> list[PointCloud]:
    return [PointCloud(points=rng.uniform((0.2, 0.2, 0.1), (5.8, 5.8, 2.9), (3000, 3)),
                       origin=(3.0 + 0.2 * k, 3.0, 1.5), range_max=4.0) for k in range(n)]


def _fused(model: type, spec: GridSpec | LatticeSpec, scans: list, threads: int) -> tuple[dict, object]:
    parallel.set_threads(threads)
    m = model(spec, SensorModel(range_sigma=0.05))
    stats = [m.integrate_batch(scans[i: i + 3]) for i in range(0, len(scans), 3)]
    return m.to_arrays(), stats


@pytest.fixture
def small_splits(monkeypatch):
    """Split work of a few hundred rays or cells (the default keeps small work in one thread)."""
    monkeypatch.setattr(parallel, "MIN_PER_THREAD", 64)
    threads = parallel.threads()
    yield
    parallel.set_threads(threads)


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize(("model", "extent"), [(FuzzyMap, "box"), (FuzzyMap, "growing"), (BayesMap, "box")])
def test_a_fusion_split_between_threads_gives_the_map_of_one_thread(model, ndim, extent, small_splits) -> None:
    rng = np.random.default_rng(11)
    scans = _room_scans(rng, 7) if ndim == 2 else _clouds(rng, 5)
    spec = (GridSpec(origin=(0.0,) * ndim, size=(6.0, 6.0, 3.0)[:ndim], resolution=0.05 if ndim == 2 else 0.1)
            if extent == "box" else LatticeSpec(ndim, 0.05 if ndim == 2 else 0.1))
    one, one_stats = _fused(model, spec, scans, 1)
    for threads in (2, 3):
        split, split_stats = _fused(model, spec, scans, threads)
        assert split.keys() == one.keys()
        for key, value in one.items():
            assert split[key].dtype == value.dtype and np.array_equal(split[key], value), (threads, key)
        assert split_stats == one_stats  # the same rays, cells walked and updated


def test_work_is_split_only_when_each_thread_gets_enough(small_splits) -> None:
    parallel.set_threads(2)
    assert parallel.walks_for(10) == 1
    assert parallel.walks_for(64 * 2) == 2
    assert parallel.walks_for(64 * 50) == 2  # never more than the threads
    parallel.set_threads(1)
    assert parallel.walks_for(64 * 50) == 1
    with pytest.raises(ValueError, match="at least 1"):
        parallel.set_threads(0)


def test_the_parts_of_a_split_run_at_the_priority_of_the_thread_that_split_them(small_splits) -> None:
    # a service fuses heavy batches in niced threads so that they take only the CPU others leave: their parts
    # must not come back at full priority in the pool
    parallel.set_threads(2)

    def nice_of_parts(nice: int) -> list[int]:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
        return parallel.run(lambda _: os.getpriority(os.PRIO_PROCESS, threading.get_native_id()), range(2))

    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    with ThreadPoolExecutor(1) as normal, ThreadPoolExecutor(1) as niced:
        assert niced.submit(nice_of_parts, base + 5).result() == [base + 5, base + 5]
        assert normal.submit(nice_of_parts, base).result() == [base, base]
