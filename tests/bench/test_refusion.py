"""The instruments of ``bench/bench_refusion.py``, CI-sized and without times: the drift it simulates, and the
corrected trajectory it PUTs, which must be what ``GET /maps/{name}/trajectory`` gives of the same scans and must
place drifted scans, as the service places them, into the corrected map bit for bit (so that the bench's
"identical" can hold)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from app.maps import logcodec
from app.reads.trajectory import trajectory_json
from app.schemas import Trajectory
from bench import _logmaps, bench_refusion
from fuzzyocc import FuzzyMap
from fuzzyocc.trajectory import Trajectory as SensorTrack
from fuzzyocc.trajectory import laser_poses
from tests.conftest import carmen_log

SCANS = 60  # orebro's first scans: a second of fusion


@pytest.fixture(scope="module")
def orebro() -> list:  # type: ignore[type-arg]
    return _logmaps.load(carmen_log("orebro-corrected.log.gz"))[:SCANS]


class _Draws:
    """A generator whose normal draws are all ``value``: the drift's rule without its randomness."""

    def __init__(self, value: float) -> None:
        self.value = value

    def normal(self, loc: float, scale: float, size: int) -> np.ndarray:
        return np.full(size, loc + scale * self.value)


def _square() -> np.ndarray:
    """A robot driving 1 m steps east, turning left on the spot, then 1 m steps north."""
    return np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 0.0, math.pi / 2],
                     [2.0, 1.0, math.pi / 2], [2.0, 2.0, math.pi / 2]])


def test_without_noise_the_drift_gives_the_poses_back() -> None:
    poses = _square()
    assert np.allclose(bench_refusion.drift_poses(poses, _Draws(0.0)), poses, atol=1e-12)  # type: ignore[arg-type]


def test_the_drift_grows_with_the_distance_and_turns_what_follows() -> None:
    poses = _square()
    walked = bench_refusion.drift_poses(poses, _Draws(1.0))  # type: ignore[arg-type]
    degree = math.radians(1.0)
    # the heading: 1 degree a metre, none for the turn on the spot
    assert walked[:, 2] - poses[:, 2] == pytest.approx([0, degree, 2 * degree, 2 * degree, 3 * degree, 4 * degree])
    # the first step: 2 % longer and 2 % to the left; the second starts turned by a degree
    assert walked[1, :2] == pytest.approx([1.02, 0.02])
    c, s = math.cos(degree), math.sin(degree)
    assert walked[2, :2] == pytest.approx([1.02 + 1.02 * c - 0.02 * s, 0.02 + 1.02 * s + 0.02 * c])
    assert walked[0] == pytest.approx(poses[0])


def test_a_log_drifts_the_same_on_every_run_and_differently_for_each_log(orebro: list) -> None:  # type: ignore[type-arg]
    one = bench_refusion.drifted(orebro, bench_refusion.log_seed("orebro"))
    again = bench_refusion.drifted(orebro, bench_refusion.log_seed("orebro"))
    other = bench_refusion.drifted(orebro, bench_refusion.log_seed("seattle"))
    assert [s.pose for s in one.scans] == [s.pose for s in again.scans]
    assert [s.pose for s in one.scans] != [s.pose for s in other.scans]
    assert one.worst_m > 0.1 and one.worst_heading_rad > math.radians(1.0)  # a drift a map shows
    for moved, scan in zip(one.scans, orebro):
        assert moved.stamp_ns == scan.stamp_ns and np.array_equal(moved.ranges, scan.ranges)


def test_the_path_put_is_the_trajectory_the_service_gives_of_the_same_scans(orebro: list) -> None:  # type: ignore[type-arg]
    log = [(1, logcodec.encode(orebro[:32])), (2, logcodec.encode(orebro[32:]))]
    given = Trajectory.model_validate_json(trajectory_json(log, moved={}, frame_id="map", stamp={"sec": 0, "nanosec": 0},
                                                           version=2, from_version=0, max_poses=1000))
    put = Trajectory.model_validate({**bench_refusion.sensor_path(orebro), "version": 2, "from_version": 0,
                                     "unstamped": 0})
    assert put.poses == given.poses and put.header.frame_id == "map"


def test_drifted_scans_reposed_on_the_path_fuse_into_the_corrected_map(orebro: list) -> None:  # type: ignore[type-arg]
    spec = _logmaps.grid_for(orebro)
    path = bench_refusion.sensor_path(orebro)["poses"]
    track = SensorTrack([p["header"]["stamp"]["sec"] * 10**9 + p["header"]["stamp"]["nanosec"] for p in path],
                        [list(p["pose"]["position"].values()) for p in path],
                        [list(p["pose"]["orientation"].values()) for p in path])
    moved = bench_refusion.drifted(orebro, bench_refusion.log_seed("orebro")).scans
    at = track.poses_at([s.stamp_ns for s in moved])
    assert at.inside.all()
    # as the service places them (app.maps.correction): the heading nearest the scan's before
    poses = laser_poses(at.positions, at.quaternions, [s.pose[2] for s in moved])
    reposed = [dataclasses.replace(s, pose=(float(x), float(y), float(t))) for s, (x, y, t) in zip(moved, poses)]
    maps = [FuzzyMap(spec) for _ in range(3)]
    for m, scans in zip(maps, (orebro, reposed, moved)):
        _logmaps.fuse(m, scans, batch=bench_refusion.BATCH)
    assert np.array_equal(maps[1].risk(), maps[0].risk())
    assert not np.array_equal(maps[2].risk(), maps[0].risk())  # the drift moved the map
