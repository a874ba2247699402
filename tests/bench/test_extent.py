"""The instruments of ``bench/bench_extent.py``, CI-sized and without times: the boxes it fuses the same scans
into walk the same cells as the growing map, its cell-for-cell check can fail, and the Ouster frames are read
as their README says."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

from bench import _logmaps, bench_extent
from fuzzyocc import FuzzyMap
from fuzzyocc.maps import Window
from tests.conftest import DATA_DIR, carmen_log, ouster_frames

SCANS = 60  # orebro's first scans: a few seconds


@pytest.fixture(scope="module")
def orebro() -> list:  # type: ignore[type-arg]
    return _logmaps.load(carmen_log("orebro-corrected.log.gz"))[:SCANS]


def test_the_three_maps_of_a_log_hold_the_same_cells(orebro: list) -> None:  # type: ignore[type-arg]
    growing = bench_extent._growing(2)
    grown = bench_extent.fuse(growing, orebro)
    bounds = growing.bounds()
    assert bounds is not None
    wide = bench_extent.box_around(bounds)
    assert wide is not None
    assert wide.shape == (8000, 8000) and wide.size == pytest.approx((400.0, 400.0))
    # the wide box holds the bounds, its corner on the growing map's lattice
    corner = np.asarray(wide.origin) / bounds.resolution
    assert np.allclose(corner, np.round(corner), atol=1e-6)
    assert all(o <= b for o, b in zip(wide.origin, bounds.origin))
    assert all(u >= b for u, b in zip(wide.upper, bounds.upper))
    own = bench_extent.own_box(bounds)
    assert own.origin == bounds.origin and own.shape == bounds.shape
    for spec in (own, wide):
        fixed = FuzzyMap(spec)
        fused = bench_extent.fuse(fixed, orebro)
        assert fused.updated == grown.updated
        assert bench_extent.same_cells(fixed, growing, bounds)
        assert bench_extent.same_cells(growing, fixed, bounds)


def test_same_cells_sees_a_map_that_differs(orebro: list) -> None:  # type: ignore[type-arg]
    full, short = bench_extent._growing(2), bench_extent._growing(2)
    bench_extent.fuse(full, orebro)
    bench_extent.fuse(short, orebro[:-1])
    bounds = full.bounds()
    assert bounds is not None
    assert not bench_extent.same_cells(short, full, bounds)


def test_no_wide_box_around_bounds_wider_than_it() -> None:
    bounds = Window(lo=(0, 0), hi=(8001, 10), resolution=0.05, lower=(0.0, 0.0))
    assert bench_extent.box_around(bounds) is None
    assert bench_extent.box_around(Window(lo=(0, 0), hi=(8000, 10), resolution=0.05, lower=(0.0, 0.0))) is not None


@pytest.mark.parametrize("packed", [False, True], ids=["velodyne-bin", "bin-gz"])
def test_ouster_frames_are_placed_by_their_poses(tmp_path: Path, packed: bool) -> None:
    """Two frames in either KITTI layout (``../shared/data/ouster``'s, ``tests/data/ouster``'s): rows at the origin
    are dropped, the others are ``R @ p + t`` with the frame's sensor position as origin."""
    rows = np.array([[1.0, 2.0, 3.0, 7.0], [0.0, 0.0, 0.0, 0.0], [-4.0, 0.5, 1.0, 9.0]], dtype=np.float32)
    if not packed:
        (tmp_path / "velodyne").mkdir()
    for i in range(2):
        if packed:
            (tmp_path / f"{i:06d}.bin.gz").write_bytes(gzip.compress(rows.tobytes()))
        else:
            rows.tofile(tmp_path / "velodyne" / f"{i:06d}.bin")
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    poses = [np.hstack([np.eye(3), np.zeros((3, 1))]), np.hstack([quarter, [[10.0], [20.0], [1.0]]])]
    np.savetxt(tmp_path / "poses.txt", np.array([p.reshape(-1) for p in poses]))
    clouds = bench_extent.ouster_clouds(tmp_path)
    assert len(clouds) == 2
    np.testing.assert_allclose(clouds[0].points, [[1.0, 2.0, 3.0], [-4.0, 0.5, 1.0]])
    np.testing.assert_allclose(clouds[1].points, [[8.0, 21.0, 4.0], [9.5, 16.0, 2.0]])
    assert clouds[1].origin == (10.0, 20.0, 1.0)
    assert clouds[1].range_max == bench_extent.OUSTER_RANGE_MAX


def test_the_repositorys_ouster_frames_are_the_shared_ones() -> None:
    """``tests/data/ouster`` (gzipped) reads as the frames ``tests/conftest.py`` hands the service tests."""
    clouds = bench_extent.ouster_clouds(DATA_DIR / "ouster")
    frames = ouster_frames()
    assert len(clouds) == len(frames) == 3
    for cloud, (points, rotation, translation) in zip(clouds, frames):
        np.testing.assert_allclose(cloud.points, points @ rotation.T + translation)
        assert cloud.origin == tuple(translation)
