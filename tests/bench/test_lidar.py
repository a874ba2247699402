"""``bench/bench_lidar.py``, CI-sized and without times: the clouds it posts are the clouds the service fuses (the
in-process peer's clouds, bit for bit, at the stamps and poses of a drive), and its quick run acknowledges every
cloud, ends with the service's map equal to the in-process one, and prints its figures and targets."""

from __future__ import annotations

import re

import numpy as np
import pytest

from app.ros import messages_in
from app.scans import Limits
from bench import bench_lidar
from tests.conftest import DATA_DIR

LIMITS = Limits(max_scans=1, max_rays=2_000_000)


@pytest.fixture(scope="module")
def ouster() -> bench_lidar.Source:
    sweeps = bench_lidar.ouster_sweeps(DATA_DIR / "ouster")
    return bench_lidar.Source("ouster", sweeps, bench_lidar.LOOP_SHIFT_M, bench_lidar.OUSTER_FORGET_BEYOND_M)


def test_a_posted_cloud_is_the_cloud_fused_in_process(ouster: bench_lidar.Source) -> None:
    """Cloud 4 (the second frame of the second loop) read from its body and query as the service reads them."""
    k, t0 = 4, 1_796_000_000_000_000_000
    body, query = ouster.body(k, t0), ouster.query(k)
    media = messages_in.media_type(messages_in.POINT_CLOUD2).lower()  # the service compares media types lower-case
    (served,) = messages_in.from_cdr(body, media, {name: str(v) for name, v in query.items()}, 3, LIMITS)
    ours = ouster.cloud(k)
    assert np.array_equal(served.points, ours.points) and served.origin == ours.origin
    assert served.range_max == ours.range_max == bench_lidar.RANGE_MAX_M
    assert served.stamp_ns == t0 + 400_000_000  # 10 Hz


def test_each_loop_of_the_frames_lies_200_m_farther_along_x(ouster: bench_lidar.Source) -> None:
    frames = len(ouster.sweeps)
    assert frames == 3
    for k in range(frames):
        here, next_loop = np.array(ouster.position(k)), np.array(ouster.position(k + frames))
        assert np.allclose(next_loop - here, [bench_lidar.LOOP_SHIFT_M, 0.0, 0.0], rtol=0.0, atol=1e-9)
        shifted = ouster.cloud(k + frames).points - ouster.cloud(k).points
        assert np.allclose(shifted, [bench_lidar.LOOP_SHIFT_M, 0.0, 0.0], rtol=0.0, atol=1e-9)
    assert not np.any(np.all(ouster.sweeps[0].rows[:, :3] == 0.0, axis=1))  # no-return rows dropped


def test_a_case_is_kind_at_resolution() -> None:
    assert bench_lidar.parse_cases("ouster@0.1, os1-128@0.2") == [("ouster@0.1", "ouster", 0.1),
                                                                  ("os1-128@0.2", "os1-128", 0.2)]
    with pytest.raises(ValueError, match="KIND@RESOLUTION"):
        bench_lidar.parse_cases("velodyne@0.1")


@pytest.mark.slow
def test_the_quick_run_acknowledges_every_cloud_and_holds_the_clouds_cells(capsys: pytest.CaptureFixture[str]) -> None:
    # a 1 s stream instead of the quick run's 3 s: every case still acknowledges clouds under load and is compared
    # with the in-process map, cell for cell; a longer stream only adds clouds to post and fuse again in-process
    assert bench_lidar.main(["--quick", "--seconds", "1", "--data", str(DATA_DIR)]) == 0
    out = capsys.readouterr().out
    acknowledged = re.findall(r"over HTTP: (\d+) clouds acknowledged of (\d+) sent", out)
    assert len(acknowledged) == len(bench_lidar.QUICK_CASES)
    assert all(int(got) == int(sent) >= 1 for got, sent in acknowledged)
    assert out.count("the service's map the in-process one, cell for cell: yes") == len(bench_lidar.QUICK_CASES)
    for figure in ("clouds/s", "M rays/s", "post latency p50", "in-process / OctoMap", "plan p99", "read p99",
                   "CPU s over the stream"):
        assert out.count(figure) >= len(bench_lidar.QUICK_CASES), figure
    (targets,) = [line for line in out.splitlines() if line.startswith("targets: ")]
    assert targets.count("met") + targets.count("not measured") >= 5  # each target with its verdict
