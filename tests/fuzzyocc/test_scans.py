import math

import numpy as np
import pytest

from fuzzyocc.scans import LaserScan, PointCloud


def _scan(**overrides: object) -> LaserScan:
    fields: dict[str, object] = dict(pose=(1.0, 2.0, 0.5), angle_min=-0.2, angle_increment=0.1,
                                     ranges=[1.0, 2.0, 3.0], range_min=0.1, range_max=10.0)
    fields.update(overrides)
    return LaserScan(**fields)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("pose", (np.nan, 0.0, 0.0)),
        ("pose", (0.0, np.inf, 0.0)),
        ("pose", (0.0, 0.0)),
        ("angle_min", np.nan),
        ("angle_increment", 0.0),
        ("angle_increment", np.inf),
        ("ranges", [[1.0, 2.0]]),
        ("ranges", ["a", "b"]),
        ("range_min", -0.1),
        ("range_min", np.nan),
        ("range_max", np.inf),
        ("range_max", 0.1),
        ("registration_sigma", -1.0),
    ],
)
def test_laser_scan_rejects_bad_fields_by_name(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        _scan(**{field: value})


def test_beam_cap_is_enforced_and_overridable() -> None:
    with pytest.raises(ValueError, match="ranges"):
        _scan(ranges=np.ones(5), max_rays=4)
    assert _scan(ranges=np.ones(5), max_rays=5).to_rays().ranges.size == 5
    with pytest.raises(ValueError, match="points"):
        PointCloud(points=np.ones((3, 2)), origin=(0.0, 0.0), range_max=5.0, max_rays=2)


def test_rep117_readings() -> None:
    rmax = 10.0
    ranges = [1.0, np.inf, -np.inf, np.nan, 0.05, rmax, rmax + 1.0, 2.0]
    rays = _scan(ranges=ranges, range_max=rmax, pose=(1.0, 2.0, 0.5)).to_rays()
    kept = [0, 1, 5, 6, 7]
    assert rays.skipped == 3  # -inf, NaN, below range_min
    assert rays.hit.tolist() == [True, False, False, False, True]
    assert rays.ranges.tolist() == [1.0, rmax, rmax, rmax, 2.0]
    angles = 0.5 - 0.2 + 0.1 * np.array(kept)
    np.testing.assert_allclose(rays.directions, np.stack([np.cos(angles), np.sin(angles)], axis=1))
    np.testing.assert_allclose(rays.endpoints[0], [1.0 + math.cos(0.3), 2.0 + math.sin(0.3)])


def test_json_null_reading_is_skipped_like_nan() -> None:
    rays = _scan(ranges=[1.0, None, 2.0]).to_rays()
    assert rays.skipped == 1
    assert rays.ranges.tolist() == [1.0, 2.0]


def test_negative_increment_scans_clockwise() -> None:
    rays = _scan(pose=(0.0, 0.0, 0.0), angle_min=0.0, angle_increment=-math.pi / 2, ranges=[1.0, 1.0]).to_rays()
    np.testing.assert_allclose(rays.endpoints, [[1.0, 0.0], [0.0, -1.0]], atol=1e-12)


def test_scans_are_immutable_snapshots_of_the_callers_arrays() -> None:
    ranges = np.array([1.0, 2.0])
    scan = _scan(ranges=ranges)
    ranges[0] = 99.0
    assert scan.ranges[0] == 1.0
    with pytest.raises(ValueError):
        scan.ranges[0] = 5.0
    with pytest.raises(AttributeError):
        scan.range_max = 3.0  # type: ignore[misc]


def test_point_cloud_cuts_far_points_at_range_max_and_skips_the_origin() -> None:
    cloud = PointCloud(points=[[3.0, 0.0, 1.0], [1.0, 20.0, 1.0], [1.0, 0.0, 1.0]], origin=(1.0, 0.0, 1.0), range_max=5.0)
    rays = cloud.to_rays()
    assert rays.skipped == 1
    assert rays.hit.tolist() == [True, False]
    np.testing.assert_allclose(rays.endpoints, [[3.0, 0.0, 1.0], [1.0, 5.0, 1.0]])


def test_point_at_range_max_is_a_hit() -> None:
    rays = PointCloud(points=[[5.0, 0.0]], origin=(0.0, 0.0), range_max=5.0).to_rays()
    assert rays.hit.tolist() == [True]


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        (dict(points=[[np.nan, 0.0, 0.0]]), "points"),
        (dict(points=[[1.0, 0.0, 0.0, 0.0]]), "points"),
        (dict(points=[1.0, 2.0]), "points"),
        (dict(origin=(0.0, 0.0)), "origin"),
        (dict(origin=(0.0, np.nan, 0.0)), "origin"),
        (dict(range_max=0.0), "range_max"),
        (dict(range_max=np.nan), "range_max"),
        (dict(registration_sigma=np.inf), "registration_sigma"),
    ],
)
def test_point_cloud_rejects_bad_fields_by_name(kwargs: dict, field: str) -> None:
    fields = dict(points=[[1.0, 0.0, 0.0]], origin=(0.0, 0.0, 0.0), range_max=5.0)
    fields.update(kwargs)
    with pytest.raises(ValueError, match=field):
        PointCloud(**fields)


def test_from_sensor_frame_applies_the_pose() -> None:
    yaw90 = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
    cloud = PointCloud.from_sensor_frame([[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]], position=(1.0, 2.0, 0.5),
                                         quaternion_xyzw=[2.0 * q for q in yaw90], range_max=30.0)
    np.testing.assert_allclose(cloud.points, [[1.0, 3.0, 0.5], [1.0, 2.0, 2.5]], atol=1e-12)
    assert cloud.origin == (1.0, 2.0, 0.5)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        (dict(quaternion_xyzw=[0.0, 0.0, 0.0, 0.0]), "quaternion_xyzw"),
        (dict(quaternion_xyzw=[0.0, 0.0, np.nan, 1.0]), "quaternion_xyzw"),
        (dict(position=(0.0, np.inf, 0.0)), "position"),
        (dict(points_sensor=[[1.0, 0.0]]), "points"),
    ],
)
def test_from_sensor_frame_rejects_bad_input(kwargs: dict, field: str) -> None:
    fields = dict(points_sensor=[[1.0, 0.0, 0.0]], position=(0.0, 0.0, 0.0), quaternion_xyzw=[0, 0, 0, 1], range_max=5.0)
    fields.update(kwargs)
    with pytest.raises(ValueError, match=field):
        PointCloud.from_sensor_frame(**fields)


@pytest.mark.parametrize("stamp", [-1, 1.5, 2.0, "5", True])
def test_a_stamp_is_whole_nanoseconds_never_negative(stamp: object) -> None:
    with pytest.raises(ValueError, match="stamp_ns"):
        _scan(stamp_ns=stamp)
    with pytest.raises(ValueError, match="stamp_ns"):
        PointCloud(points=[[1.0, 0.0]], origin=(0.0, 0.0), range_max=5.0, stamp_ns=stamp)


def test_a_scan_keeps_its_stamp_and_takes_another_without_a_copy_of_its_beams() -> None:
    scan = _scan(stamp_ns=np.int64(1_700_000_000_123_456_789))
    assert scan.stamp_ns == 1_700_000_000_123_456_789 and type(scan.stamp_ns) is int
    assert _scan().stamp_ns is None  # unstamped unless given
    later = scan.stamped(1_700_000_000_323_456_789)
    assert later.stamp_ns == 1_700_000_000_323_456_789 and scan.stamp_ns == 1_700_000_000_123_456_789
    assert later.ranges is scan.ranges and later.pose == scan.pose
    with pytest.raises(ValueError, match="stamp_ns"):
        scan.stamped(-5)
    cloud = PointCloud.from_sensor_frame([[1.0, 0.0, 0.0]], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0], 5.0, stamp_ns=42)
    assert cloud.stamp_ns == 42 and cloud.stamped(None).stamp_ns is None
