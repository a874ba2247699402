"""fuzzyocc.trajectory: a corrected trajectory's poses at the scans' stamps, as tf2 gives them, and scans re-posed."""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fuzzyocc import FuzzyMap, GridSpec, LaserScan, PointCloud
from fuzzyocc.carmen import grid_for_scans, read_carmen
from fuzzyocc.tf import NotLevel, level_heading, yaw_quaternion
from fuzzyocc.trajectory import Trajectory, laser_poses, repose

CARMEN = Path(__file__).resolve().parents[1] / "data" / "carmen"
#: Past float64's exact integers (2**53): the interpolation must work on nanoseconds since the first stamp.
T0 = 1_700_000_000 * 10**9
MS = 1_000_000


def _yaw(angle: float) -> np.ndarray:
    return np.array(yaw_quaternion(angle))


def _tf2_slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """tf2's ``Quaternion::slerp`` written out: the shorter way round (q1 negated when the two point apart)."""
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    dot = float(q0 @ q1)
    sign = 1.0 if dot >= 0.0 else -1.0
    omega = math.acos(min(abs(dot), 1.0))
    return (math.sin((1.0 - u) * omega) * q0 + sign * math.sin(u * omega) * q1) / math.sin(omega)


def _same_rotation(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(min(np.abs(a - b).max(), np.abs(a + b).max()) < 1e-12)  # q and -q are one rotation


def _away_from(q: np.ndarray, rotation: Rotation) -> np.ndarray:
    """``rotation`` as the quaternion of its two whose dot product with ``q`` is negative."""
    out = rotation.as_quat()
    return out if out @ q < 0.0 else -out


#: Three samples: a yaw, a rotation about every axis, and one written pointing away from it (the shorter way
#: round goes through its negation).
Q0 = _yaw(0.2)
Q1 = Rotation.from_euler("xyz", [0.3, -0.2, 1.4]).as_quat()
Q2 = _away_from(Q1, Rotation.from_euler("xyz", [0.1, 0.05, -2.9]))
PATH = Trajectory([T0, T0 + 100 * MS, T0 + 300 * MS], [[0.0, 0.0, 0.0], [1.0, 2.0, 0.5], [-3.0, 6.0, 0.1]],
                  [Q0, Q1, Q2])


def test_a_stamp_between_two_poses_gets_the_translation_linearly_and_the_rotation_by_tf2s_slerp() -> None:
    at = PATH.poses_at([T0 + 50 * MS, T0 + 150 * MS])  # the first interval's midpoint, the second's quarter
    assert at.inside.tolist() == [True, True]
    np.testing.assert_allclose(at.positions[0], [0.5, 1.0, 0.25], rtol=0, atol=1e-15)
    np.testing.assert_allclose(at.positions[1], [0.0, 3.0, 0.4], rtol=0, atol=1e-15)
    assert _same_rotation(at.quaternions[0], _tf2_slerp(Q0, Q1, 0.5))
    assert _same_rotation(at.quaternions[1], _tf2_slerp(Q1, Q2, 0.25))


def test_a_stamp_to_the_nanosecond_is_interpolated_to_the_nanosecond() -> None:
    u = 7_777_777 / (100 * MS)
    at = PATH.poses_at([T0 + 7_777_777])
    np.testing.assert_allclose(at.positions[0], [u, 2.0 * u, 0.5 * u], rtol=0, atol=1e-15)
    assert _same_rotation(at.quaternions[0], _tf2_slerp(Q0, Q1, u))


def test_a_stamp_equal_to_a_poses_gets_that_pose_bit_for_bit() -> None:
    # a quaternion 5e-4 off unit, as a float32 message gives it: returned as given, not normalised
    q = Rotation.from_euler("z", 0.7).as_quat() * (1.0 + 5e-4)
    path = Trajectory([10, 20, 30], [[0.1, 0.2, 0.3], [1 / 3, 2 / 7, 0.0], [5.0, 5.0, 5.0]], [Q0, q, Q1])
    at = path.poses_at([20, 10, 30, 20])
    assert at.inside.all()
    assert at.positions.tobytes() == path.positions[[1, 0, 2, 1]].tobytes()
    assert at.quaternions.tobytes() == path.quaternions[[1, 0, 2, 1]].tobytes()


def test_a_stamp_outside_the_path_is_flagged_not_extrapolated() -> None:
    at = PATH.poses_at([T0 - 1, T0 + 300 * MS + 1, 0, T0])
    assert at.inside.tolist() == [False, False, False, True]
    assert np.isnan(at.positions[:3]).all() and np.isnan(at.quaternions[:3]).all()
    one = Trajectory([T0], [[1.0, 2.0, 3.0]], [Q1])  # one pose: its stamp only
    assert one.poses_at([T0 - 1, T0, T0 + 1]).inside.tolist() == [False, True, False]


def _matrix(position: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The homogeneous matrix of a pose, from the quaternion by its textbook formula (not scipy)."""
    x, y, z, w = q / np.linalg.norm(q)
    out = np.eye(4)
    out[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                   [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                   [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    out[:3, 3] = position
    return out


def test_a_sensor_offset_composes_each_pose_with_it_as_matrices_do() -> None:
    # a laser 0.3 m ahead, 0.1 m left and 0.2 m up on the robot, rolled upside down and turned a little
    offset_p = np.array([0.3, 0.1, 0.2])
    offset_q = Rotation.from_euler("xyz", [math.pi, 0.0, 0.1]).as_quat()
    sensor = PATH.with_offset(offset_p, offset_q)
    assert sensor.stamps_ns.tolist() == PATH.stamps_ns.tolist()
    for k in range(len(PATH)):
        expected = _matrix(PATH.positions[k], PATH.quaternions[k]) @ _matrix(offset_p, offset_q)
        np.testing.assert_allclose(_matrix(sensor.positions[k], sensor.quaternions[k]), expected, rtol=0, atol=1e-14)


@pytest.mark.parametrize(("stamps", "positions", "quaternions", "message"), [
    ([0, 10, 10, 30], None, None, r"stamps_ns\[2\] \(10\) is not after stamps_ns\[1\] \(10\)"),
    ([0, 10, 30, 20], None, None, r"stamps_ns\[3\] \(20\) is not after stamps_ns\[2\] \(30\)"),
    ([0, -10, 20, 30], None, None, r"stamps_ns\[1\] is -10: ROS time is never negative"),
    ([0.0, 10.0, 20.0, 30.0], None, None, "stamps_ns must be integer nanoseconds"),
    (None, {1: [0.0, math.nan, 0.0]}, None, r"positions\[1\] must be finite"),
    (None, {3: [math.inf, 0.0, 0.0]}, None, r"positions\[3\] must be finite"),
    (None, None, {2: [0.0, 0.0, math.nan, 1.0]}, r"quaternions\[2\] must be finite"),
    (None, None, {1: [0.0, 0.0, 0.0, 1.0011]}, r"quaternions\[1\] must be a unit quaternion .* norm is 1\.0011"),
    (None, None, {0: [0.0, 0.0, 0.0, 0.0]}, r"quaternions\[0\] must be a unit quaternion .* norm is 0"),
])
def test_a_bad_trajectory_is_refused_naming_the_field_and_index(
        stamps: list[float] | None, positions: dict[int, list[float]] | None,
        quaternions: dict[int, list[float]] | None, message: str) -> None:
    p, q = np.zeros((4, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (4, 1))
    for k, row in (positions or {}).items():
        p[k] = row
    for k, row in (quaternions or {}).items():
        q[k] = row
    with pytest.raises(ValueError, match=message):
        Trajectory(stamps or [0, 10, 20, 30], p, q)


def test_a_quaternion_as_far_from_unit_as_a_json_scan_pose_may_be_is_taken() -> None:
    q = np.array([0.0, 0.0, 0.0, 1.0009])  # a scan's Pose3D takes norms within 1e-3 of 1: the same rule
    path = Trajectory([0], [[0.0, 0.0, 0.0]], [q])
    assert path.poses_at([0]).quaternions[0].tobytes() == q.tobytes()
    with pytest.raises(ValueError, match=r"offset quaternion_xyzw\[0\] must be a unit quaternion"):
        path.with_offset([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0011])


def _scan(pose: tuple[float, float, float] = (1.0, 2.0, 0.5)) -> LaserScan:
    return LaserScan(pose=pose, angle_min=-1.0, angle_increment=0.25, ranges=[2.0, math.inf, 3.0, math.nan, 1.5],
                     range_min=0.1, range_max=10.0, registration_sigma=0.02, stamp_ns=T0)


def test_a_laser_scan_reposed_keeps_its_beams_and_stamp_and_takes_the_poses_heading() -> None:
    scan = _scan()
    # rolled 2 degrees (within the level tolerance) and turned 1.1 rad; z is not a LaserScan's
    q = Rotation.from_euler("ZYX", [1.1, 0.0, math.radians(2.0)]).as_quat()
    out = repose(scan, [4.0, -1.0, 0.7], q)
    assert out.pose[:2] == (4.0, -1.0) and out.pose[2] == pytest.approx(1.1, abs=1e-15)
    assert out.ranges.tobytes() == scan.ranges.tobytes() and out.stamp_ns == scan.stamp_ns
    assert (out.angle_min, out.angle_increment, out.range_min, out.range_max, out.registration_sigma) == \
        (scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max, scan.registration_sigma)


def test_an_upside_down_scanner_is_reposed_with_its_beams_as_stored() -> None:
    # a LaserScan from a scanner upside down was stored with its angles negated: they stay, theta is the heading
    q = Rotation.from_euler("ZYX", [-0.4, 0.0, math.pi]).as_quat()
    out = repose(_scan(), [0.0, 0.0, 0.0], q)
    assert out.pose[2] == pytest.approx(-0.4, abs=1e-15) and level_heading(q)[1] == -1.0
    assert (out.angle_min, out.angle_increment) == (-1.0, 0.25)


def test_a_tilted_pose_or_a_cloud_is_not_reposed() -> None:
    with pytest.raises(NotLevel, match=r"tilted 10\.0 degrees from level"):
        repose(_scan(), [0.0, 0.0, 0.0], Rotation.from_euler("x", math.radians(10.0)).as_quat())
    with pytest.raises(ValueError, match=r"position\[0\] must be finite"):
        repose(_scan(), [math.nan, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    cloud = PointCloud(points=[[1.0, 0.0, 0.0]], origin=(0.0, 0.0, 0.0), range_max=5.0, stamp_ns=T0)
    with pytest.raises(NotImplementedError, match="PointCloud cannot be re-posed"):
        repose(cloud, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])


def test_a_scans_own_heading_keeps_its_theta_bit_for_bit() -> None:
    # 4 rad is -2.28 rad once read off a quaternion: the scan keeps the theta it has
    scan = _scan((1.0, 2.0, 4.0))
    assert level_heading(_yaw(4.0))[0] != 4.0
    out = repose(scan, [3.0, 2.0, 0.0], _yaw(4.0))
    assert out.pose == (3.0, 2.0, 4.0)


def _fused(scans: list[LaserScan], spec: GridSpec) -> dict[str, np.ndarray]:
    fuzzy = FuzzyMap(spec)
    fuzzy.integrate_batch(scans)
    return fuzzy.to_arrays()


def test_reposed_scans_fuse_into_the_map_of_scans_taken_at_those_poses() -> None:
    """What a rebuild relies on: a re-posed scan is, for fusion, a scan posted at its new pose."""
    scans = read_carmen(CARMEN / "seattle-corrected.log.gz")[:40]
    # a correction of every fourth pose of the first 32: moved and turned, those between interpolated, the rest kept
    keys = scans[:32:4]
    correction = Trajectory(
        [s.stamp_ns for s in keys],
        [(s.pose[0] + 0.3 * k, s.pose[1] - 0.1 * k, 0.0) for k, s in enumerate(keys)],
        [_yaw(s.pose[2] + 0.02 * k) for k, s in enumerate(keys)])
    at = correction.poses_at([s.stamp_ns for s in scans])
    assert at.inside.sum() == 29 and not at.inside[29:].any()
    reposed = [repose(s, p, q) if inside else s
               for s, inside, p, q in zip(scans, at.inside, at.positions, at.quaternions, strict=True)]
    direct = [LaserScan(pose=(p[0], p[1], level_heading(q)[0]), angle_min=s.angle_min,
                        angle_increment=s.angle_increment, ranges=np.array(s.ranges), range_min=s.range_min,
                        range_max=s.range_max, stamp_ns=s.stamp_ns)
              if inside else s
              for s, inside, p, q in zip(scans, at.inside, at.positions, at.quaternions, strict=True)]
    spec = grid_for_scans(scans, resolution=0.1, margin=2.0)
    expected, got = _fused(direct, spec), _fused(reposed, spec)
    assert sorted(got) == sorted(expected)
    for key, value in expected.items():
        assert got[key].tobytes() == value.tobytes(), key
    assert (got["state"] != _fused(scans, spec)["state"]).any(), "the correction moved nothing"


@pytest.mark.parametrize("log", ["seattle-corrected.log.gz", "orebro-corrected.log.gz"])
def test_a_log_reposed_on_its_own_trajectory_gets_every_pose_back_exactly(log: str) -> None:
    # seattle's stamps are its own, orebro's numbered at 5 Hz; thetas run past pi, as logs write them
    scans = read_carmen(CARMEN / log)
    assert any(abs(s.pose[2]) > math.pi for s in scans), "no theta that a quaternion would wrap"
    own = Trajectory([s.stamp_ns for s in scans], [(s.pose[0], s.pose[1], 0.0) for s in scans],
                     [yaw_quaternion(s.pose[2]) for s in scans])
    at = own.poses_at([s.stamp_ns for s in scans])
    assert at.inside.all()
    for scan, p, q in zip(scans, at.positions, at.quaternions, strict=True):
        out = repose(scan, p, q)
        assert np.array(out.pose).tobytes() == np.array(scan.pose).tobytes(), scan.stamp_ns
        assert out.stamp_ns == scan.stamp_ns and out.ranges.tobytes() == scan.ranges.tobytes()


@pytest.mark.parametrize("log", ["seattle-corrected.log.gz", "orebro-corrected.log.gz", "csail-corrected.log.gz"])
def test_yaw_quaternions_of_a_logs_headings_give_the_headings_back_bit_for_bit(log: str) -> None:
    # a SLAM node publishes the corrected poses as yaw quaternions, whatever the scans' poses were before: the
    # map must get those very headings (not the ones a quaternion's yaw rounds or wraps to)
    scans = read_carmen(CARMEN / log)
    thetas = np.array([s.pose[2] for s in scans])
    quaternions = np.array([yaw_quaternion(t) for t in thetas])
    positions = np.array([[s.pose[0], s.pose[1], 0.0] for s in scans])
    drifted = thetas + np.random.default_rng(3).normal(0.0, 0.3, thetas.size)  # the headings the map had before
    got = laser_poses(positions, quaternions, drifted)
    assert np.array_equal(got[:, 2].view(np.uint64), thetas.view(np.uint64))
    assert np.array_equal(got[:, :2], positions[:, :2])


def test_laser_poses_name_the_first_tilted_pose() -> None:
    tilted = Rotation.from_euler("x", math.radians(10.0)).as_quat()
    with pytest.raises(NotLevel, match="pose 1: "):
        laser_poses(np.zeros((2, 3)), [[0.0, 0.0, 0.0, 1.0], tilted])


def test_a_trajectory_and_a_tilt_refusal_cross_a_process_as_they_were() -> None:
    """Both come back from the service's parse process by pickle: the same poses, read-only; the same refusal."""
    trajectory = Trajectory(np.array([10, 20, 30]), np.arange(9.0).reshape(3, 3), np.stack([_yaw(0.1 * i) for i in range(3)]))
    back = pickle.loads(pickle.dumps(trajectory))
    at = np.array([10, 15, 27])
    np.testing.assert_array_equal(back.poses_at(at).positions, trajectory.poses_at(at).positions)
    np.testing.assert_array_equal(back.poses_at(at).quaternions, trajectory.poses_at(at).quaternions)
    assert not back.positions.flags.writeable and not back.stamps_ns.flags.writeable
    refusal = pickle.loads(pickle.dumps(NotLevel(10.0, index=1)))
    assert (refusal.degrees, refusal.index, str(refusal)) == (10.0, 1, str(NotLevel(10.0, index=1)))
