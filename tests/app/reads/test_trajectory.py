"""``app.reads.trajectory``: the poses, written a chunk at a time, are the ``Trajectory`` the model reads, with every
number as stored."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from app.errors import TooLarge
from app.maps import logcodec
from app.reads import trajectory
from app.schemas import Trajectory
from fuzzyocc import LaserScan, PointCloud


def test_the_answer_is_a_trajectory_with_every_number_as_stored() -> None:
    rng = np.random.default_rng(8)
    lasers = [LaserScan(pose=tuple(rng.uniform(-50, 50, 3)), angle_min=-1.0, angle_increment=0.5,  # type: ignore[arg-type]
                        ranges=[1.0, 2.0, 3.0, 4.0, 5.0], range_min=0.1, range_max=8.0,
                        stamp_ns=int(rng.integers(0, 2**62)) if k % 3 else None) for k in range(5000)]
    cloud = PointCloud(points=[[1.0, 2.0, 3.0]], origin=(0.5, -0.25, 1.75), range_max=9.0, stamp_ns=12)
    log = [(3, logcodec.encode(lasers[:4500])), (5, logcodec.encode([cloud])), (6, logcodec.encode(lasers[4500:]))]
    made = trajectory.trajectory_json(log, moved={}, frame_id="robot1/map", stamp={"sec": 17, "nanosec": 4}, version=6,
                                      from_version=2, max_poses=5001)
    parsed = Trajectory.model_validate_json(made)  # the model's shape
    assert (parsed.version, parsed.from_version) == (6, 2)
    assert parsed.unstamped == sum(s.stamp_ns is None for s in lasers)
    assert parsed.header.model_dump() == {"stamp": {"sec": 17, "nanosec": 4}, "frame_id": "robot1/map"}

    def expected(scan: LaserScan | PointCloud) -> dict[str, object]:
        ns = scan.stamp_ns or 0
        header = {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": "robot1/map"}
        if isinstance(scan, PointCloud):
            x, y, z = scan.origin
            return {"header": header, "pose": {"position": {"x": x, "y": y, "z": z},
                                               "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}
        x, y, yaw = scan.pose
        return {"header": header, "pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": {
            "x": 0.0, "y": 0.0, "z": math.sin(0.5 * yaw), "w": math.cos(0.5 * yaw)}}}

    assert json.loads(made)["poses"] == [expected(s) for s in [*lasers[:4500], cloud, *lasers[4500:]]]
    with pytest.raises(TooLarge, match="FUZZYRISK_MAX_TRAJECTORY_POSES"):
        trajectory.trajectory_json(log, moved={}, frame_id="map", stamp={"sec": 0, "nanosec": 0}, version=6, from_version=2,
                                   max_poses=5000)


def test_a_map_without_scans_has_no_poses() -> None:
    made = trajectory.trajectory_json([], moved={}, frame_id="map", stamp={"sec": 1, "nanosec": 0}, version=0, from_version=0,
                                      max_poses=1)
    assert Trajectory.model_validate_json(made).poses == [] and json.loads(made)["poses"] == []
