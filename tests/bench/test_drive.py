"""The instruments of ``bench/bench_drive.py``, CI-sized and without times: the generated street, the sweeps a
robot takes in it, and the verdict on memory over time."""

from __future__ import annotations

import numpy as np
import pytest

from bench import bench_drive
from bench.bench_drive import Sample


def _inside(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float) -> np.ndarray:
    """(N,) whether each point lies in some box grown by ``margin``."""
    return np.any(np.all((points[:, None] >= lo[None] - margin) & (points[:, None] <= hi[None] + margin), axis=2),
                  axis=1)


def test_a_tile_is_the_same_whenever_it_is_made() -> None:
    a_lo, a_hi = bench_drive.tile_boxes(3, 5)
    b_lo, b_hi = bench_drive.tile_boxes(3, 5)
    assert np.array_equal(a_lo, b_lo) and np.array_equal(a_hi, b_hi)
    assert not np.array_equal(bench_drive.tile_boxes(3, 6)[1], a_hi)
    assert not np.array_equal(bench_drive.tile_boxes(4, 5)[1], a_hi)
    assert np.all(a_hi > a_lo)


def test_the_robot_drives_clear_of_every_box_but_the_ground() -> None:
    street = bench_drive.Street(seed=1)
    x = np.linspace(-50.0, 250.0, 3001)
    lo, hi = street.boxes_near(100.0, 160.0)
    above_ground = lo[:, 2] >= 0.0
    for z in (0.3, 1.0, bench_drive.SENSOR_HEIGHT_M):
        path = np.stack([x, bench_drive.centre_y(x), np.full_like(x, z)], axis=1)
        assert not _inside(path, lo[above_ground], hi[above_ground], 1.0).any()
    assert len(street.tiles) == 17  # the tiles within 160 m of x = 100, no more


def test_a_sweep_hits_the_boxes_near_the_robot() -> None:
    street = bench_drive.Street(seed=2)
    beams = bench_drive.beam_directions(16, 64)
    cloud = bench_drive.sweep(street, np.random.default_rng(0), 20.0, 1.5, beams)
    origin = np.asarray(cloud.origin)
    assert origin[0] == pytest.approx(30.0) and origin[2] == bench_drive.SENSOR_HEIGHT_M
    assert 0 < cloud.points.shape[0] < beams.shape[0]  # the sky gives no return
    lo, hi = street.boxes_near(origin[0], 2 * bench_drive.RANGE_MAX_M)
    # on a face of some box, to within the range noise (0.03 m, 5 sigma): not in free space, not deep inside
    assert _inside(cloud.points, lo, hi, 0.15).all()
    assert not _inside(cloud.points, lo, hi, -0.15).any()
    below = cloud.points[:, 2] < 0.5
    assert below.any() and (cloud.points[:, 2] > 2.0).any()  # the ground and the buildings


def _samples(values: list[float], every_s: float = 30.0) -> list[Sample]:
    return [Sample(t_s=i * every_s, held=int(v), state=int(v), resident=int(v)) for i, v in enumerate(values)]


def test_the_verdict_judges_the_state_after_the_first_minutes() -> None:
    # every 30 s for 30 minutes: rising for 2 minutes, then level, moving by 5 % either way
    level = [100_000.0 + 50_000.0 * min(i, 4) for i in range(61)]
    level = [v * (1.0 + 0.05 * np.sin(i)) if i > 4 else v for i, v in enumerate(level)]
    flat = bench_drive.flat_verdict(_samples(level), settle_min=5.0)
    assert flat.first.state == max(int(v) for v in level[1:11])
    assert flat.at_settle.t_s == 300.0 and flat.later.t_s >= 600.0
    assert flat.ratio == max(int(v) for v in level[20:]) / flat.first.state and flat.ratio <= bench_drive.FLAT_WITHIN
    assert flat.ratio_to_settle == flat.later.state / int(level[10])
    assert abs(flat.slope_mb_per_min) < 0.01
    growing = [100_000.0 + 10_000.0 * i for i in range(61)]  # 20 kB a minute
    flat = bench_drive.flat_verdict(_samples(growing), settle_min=5.0)
    assert flat.ratio == pytest.approx(700_000.0 / 200_000.0) and flat.ratio > bench_drive.FLAT_WITHIN
    assert flat.slope_mb_per_min == pytest.approx(0.02)
    with pytest.raises(ValueError, match="longer than 10 minutes"):
        bench_drive.flat_verdict(_samples(level[:20]), settle_min=5.0)
