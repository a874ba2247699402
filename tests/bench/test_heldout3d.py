"""The instruments of ``bench/bench_heldout3d.py``, CI-sized and without times: the held-out rays are the frame's
returns within ``range_max``, a fold fuses the other frames in order, both maps' casts read a known wall where it
is (and nothing beyond their reach), the 3-D march is the 2-D one on a map one cell high, and the table says
plainly where ours is worse."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from bench import _logmaps, bench_extent, bench_heldout3d
from bench._logmaps import HeldOut, Score
from bench.bench_fusion import Clock
from fuzzyocc import GridSpec, PointCloud
from tests.conftest import DATA_DIR

WALL_X = 3.05  # the middle of a cell at 0.1 m and at 0.2 m: every ray ends in the wall's own column of cells


def wall_cloud(origin: tuple[float, float, float], wall_x: float = WALL_X) -> PointCloud:
    """A sweep of 40 x 20 rays (azimuth +-30 degrees, elevation +-15) ending on the plane ``x = wall_x``."""
    azimuth, elevation = np.meshgrid(np.radians(np.linspace(-30, 30, 40)), np.radians(np.linspace(-15, 15, 20)))
    a, e = azimuth.ravel(), elevation.ravel()
    d = np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    points = np.asarray(origin) + d * ((wall_x - origin[0]) / d[:, 0])[:, None]
    return PointCloud(points=points, origin=origin, range_max=30.0)


@pytest.fixture(scope="module")
def wall_fold() -> bench_heldout3d.Fold:
    """Two sweeps of the wall fused, a third from between them held out."""
    clouds = [wall_cloud((0.0, y, 1.0)) for y in (0.0, 0.3, 0.15)]
    return bench_heldout3d.folds(clouds)[2]


def test_the_held_out_rays_are_every_strided_return_within_range_max() -> None:
    origin = (1.0, 2.0, 0.5)
    offsets = np.array([[3.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, -2.0], [30.0, 0.0, 0.0], [1.0, 1.0, 1.0],
                        [0.0, 6.0, 8.0]])
    cloud = PointCloud(points=np.asarray(origin) + offsets, origin=origin, range_max=30.0)
    every = bench_heldout3d.held_out_rays(cloud, 1)
    within = [0, 2, 4, 5]  # 40 m and exactly range_max are not returns within it
    assert np.allclose(every.ranges, np.linalg.norm(offsets[within], axis=1))
    assert np.allclose(every.origins, np.tile(origin, (4, 1)))
    assert np.allclose(every.origins + every.directions * every.ranges[:, None], np.asarray(origin) + offsets[within])
    assert np.allclose(np.linalg.norm(every.directions, axis=1), 1.0)
    second = bench_heldout3d.held_out_rays(cloud, 2)
    assert np.allclose(second.ranges, every.ranges[::2])


def test_fold_k_holds_frame_k_out_and_fuses_the_others_in_order() -> None:
    clouds = [wall_cloud((float(k), 0.0, 1.0), 10.0) for k in range(3)]
    folds = bench_heldout3d.folds(clouds)
    assert [f.held for f in folds] == [0, 1, 2]
    for f in folds:
        assert f.held_out is clouds[f.held]
        assert f.fused == [c for c in clouds if c is not clouds[f.held]]  # in the frames' order


@pytest.mark.parametrize("resolution", [0.1, 0.2])
def test_both_maps_read_a_known_wall_where_it_is(wall_fold: bench_heldout3d.Fold, resolution: float) -> None:
    """Each map of the two fused sweeps predicts every held-out ray's range to the centre of a wall cell: within half
    a cell's diagonal of the measured range."""
    rays = bench_heldout3d.held_out_rays(wall_fold.held_out, 1)
    ours, _ = bench_extent.fuse_clouds(wall_fold.fused, resolution)
    tree, _ = bench_extent.octomap_of_clouds(wall_fold.fused, resolution)
    half_diagonal = 0.5 * math.sqrt(3) * resolution + 1e-6  # OctoMap's coordinates are float32
    for predicted in (bench_heldout3d.our_ranges(ours, rays), bench_heldout3d.octomap_ranges(tree, rays)):
        assert np.all(np.abs(predicted - rays.ranges) <= half_diagonal), np.max(np.abs(predicted - rays.ranges))
    result = bench_heldout3d.run_fold(wall_fold, resolution, rays)
    for s in (result.ours, result.octomap):
        assert (s.beams, s.within, s.early, s.late, s.none) == (rays.ranges.size, 1.0, 0.0, 0.0, 0.0)


def test_a_surface_beyond_the_reach_is_none_for_both(wall_fold: bench_heldout3d.Fold) -> None:
    rays = bench_heldout3d.held_out_rays(wall_fold.held_out, 1)
    ours, _ = bench_extent.fuse_clouds(wall_fold.fused, 0.1)
    tree, _ = bench_extent.octomap_of_clouds(wall_fold.fused, 0.1)
    short = WALL_X - 0.5  # shorter than every ray to the wall
    assert np.all(np.isinf(bench_heldout3d.our_ranges(ours, rays, short)))
    assert np.all(np.isinf(bench_heldout3d.octomap_ranges(tree, rays, short)))
    assert np.all(np.isfinite(bench_heldout3d.our_ranges(ours, rays, 2 * WALL_X)))


def test_the_march_of_a_2d_map_is_the_march_of_it_one_cell_high() -> None:
    rng = np.random.default_rng(3)
    spec = GridSpec(origin=(-1.0, 0.5), size=(4.0, 3.0), resolution=0.05)
    risk = (rng.random(spec.shape) > 0.97).astype(np.float32)
    n = 500
    origins = np.asarray(spec.origin) + rng.random((n, 2)) * np.asarray(spec.size)
    angles = rng.uniform(-math.pi, math.pi, n)
    flat = HeldOut(origins, np.column_stack([np.cos(angles), np.sin(angles)]), np.ones(n))
    planar = _logmaps.predicted_ranges(risk, spec, flat)
    z = 0.5 * spec.resolution  # the height of the one layer's cell centres
    tall = HeldOut(np.column_stack([origins, np.full(n, z)]), np.column_stack([flat.directions, np.zeros(n)]),
                   flat.ranges)
    spec3 = GridSpec(origin=(*spec.origin, 0.0), size=(*spec.size, spec.resolution), resolution=spec.resolution)
    assert np.isfinite(planar).mean() > 0.5
    assert np.array_equal(planar, _logmaps.predicted_ranges(risk[:, :, None], spec3, tall))


def _result(fold: int, ours_within: float, octomap_within: float) -> bench_heldout3d.FoldResult:
    def score(within: float) -> Score:
        return Score(beams=100, within=within, early=1.0 - within, late=0.0, none=0.0, median_error=0.1)

    clock = Clock()
    clock.wall = clock.cpu = 1.0
    return bench_heldout3d.FoldResult(fold, 0.1, score(ours_within), score(octomap_within), clock, clock)


def test_the_table_says_where_ours_is_worse(capsys: pytest.CaptureFixture[str]) -> None:
    bench_heldout3d.print_table([_result(0, 0.6, 0.5), _result(1, 0.4, 0.5), _result(2, 0.7, 0.7)])
    out = capsys.readouterr().out
    assert "ours >= OctoMap's on 2 of 3 folds: ours is WORSE on the others" in out
    assert re.search(r"mean\s+0\.10\s+300 \|\s+56\.7 %", out)  # the folds' mean, their rays summed
    bench_heldout3d.print_table([_result(0, 0.6, 0.5)])
    assert "WORSE" not in capsys.readouterr().out


@pytest.mark.slow
def test_the_quick_run_scores_every_fold_on_the_frames(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench_heldout3d.main(["--quick", "--data", str(DATA_DIR)]) == 0
    out = capsys.readouterr().out
    clouds = bench_extent.ouster_clouds(DATA_DIR / "ouster")
    res = bench_heldout3d.QUICK_RESOLUTIONS[0]
    for k, cloud in enumerate(clouds):
        rays = bench_heldout3d.held_out_rays(cloud, bench_heldout3d.QUICK_STRIDE).ranges.size
        row = re.search(rf"^\s+{k}\s+{res:.2f}\s+{rays:,} \|(.*)$", out, re.MULTILINE)
        assert row is not None, out
        shares = [float(v) for v in re.findall(r"([\d.]+) %", row.group(1))]
        assert len(shares) == 8
        assert sum(shares[:4]) == pytest.approx(100.0, abs=0.3) and sum(shares[4:]) == pytest.approx(100.0, abs=0.3)
    assert re.search(rf"^mean\s+{res:.2f}", out, re.MULTILINE)
