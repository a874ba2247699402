"""CARMEN logs in: beam angles, poses and stamps, no-returns, skipped and malformed lines, the real logs of tests/data."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from fuzzyocc.carmen import (
    NO_RETURN_FRACTION,
    CarmenScan,
    grid_for_scans,
    log_stamps_ns,
    parse_carmen_lines,
    read_carmen,
)
from tests.conftest import carmen_log

#: The table of tests/data/README.md: FLASER scans and beams per scan of each log.
REAL_LOGS = {
    "acapulco-corrected.log.gz": (861, 181),
    "belgioioso-corrected.log.gz": (395, 361),
    "csail-corrected.log.gz": (406, 361),
    "edmonton-corrected.log.gz": (340, 180),
    "fhw-corrected.log.gz": (488, 180),
    "freiburg-101-corrected.log.gz": (292, 360),
    "infinite-corridor-corrected.log.gz": (1941, 180),
    "orebro-corrected.log.gz": (237, 181),
    "seattle-corrected.log.gz": (241, 361),
}


def flaser(ranges: list[float], pose: tuple[float, float, float] = (1.5, -2.25, 0.5),
           stamps: tuple[str, str] = ("1234.5", "1234.75")) -> str:
    numbers = " ".join(repr(r) for r in ranges)
    return f"FLASER {len(ranges)} {numbers} {pose[0]} {pose[1]} {pose[2]} 9 9 9 {stamps[0]} pippo {stamps[1]}"


def robotlaser(ranges: list[float], *, start: float = -2.35619, resolution: float = 0.00436332,
               max_range: float = 30.0, remissions: int = 2) -> str:
    fov = resolution * (len(ranges) - 1)
    remission = " ".join(["0.5"] * remissions)
    return (f"ROBOTLASER1 0 {start} {fov} {resolution} {max_range} 0.01 0 {len(ranges)} "
            f"{' '.join(repr(r) for r in ranges)} {remissions} {remission} "
            "3.0 4.0 1.25 2.9 3.9 1.2 0.3 0.1 0.5 0.4 0.2 77.5 host 78.25")


def write_log(tmp_path: Path, lines: list[str], name: str = "test.log") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


# ---------------------------------------------------------------- FLASER geometry


@pytest.mark.parametrize(("beams", "last"), [(180, math.pi / 2 - math.pi / 180), (181, math.pi / 2),
                                             (360, math.pi / 2 - math.pi / 360), (361, math.pi / 2)])
def test_flaser_beams_span_180_degrees_from_the_right(beams: int, last: float) -> None:
    (scan,) = parse_carmen_lines([flaser([2.0] * beams)])
    assert scan.angle_min == -math.pi / 2
    assert scan.angle_min + (beams - 1) * scan.angle_increment == pytest.approx(last, abs=1e-12)
    step_degrees = 1.0 if beams in (180, 181) else 0.5
    assert math.degrees(scan.angle_increment) == pytest.approx(step_degrees, abs=1e-12)


def test_flaser_pose_and_stamp_and_where_the_beams_land() -> None:
    ranges = [1.0] + [5.0] * 179 + [2.0]  # 181 beams: first to the right, last to the left
    (raw,) = parse_carmen_lines([flaser(ranges, pose=(1.5, -2.25, 0.0))])
    assert raw.pose == (1.5, -2.25, 0.0)
    assert raw.stamp == 1234.75  # the logger's timestamp, not the IPC one
    assert raw.line == 1 and raw.max_range is None
    scan = raw.to_laser_scan(range_max=50.0)
    ends = scan.to_rays().endpoints
    np.testing.assert_allclose(ends[0], [1.5, -3.25], atol=1e-12)   # 1 m to the robot's right
    np.testing.assert_allclose(ends[90], [6.5, -2.25], atol=1e-12)  # 5 m straight ahead
    np.testing.assert_allclose(ends[180], [1.5, -0.25], atol=1e-12)  # 2 m to its left


def test_a_flaser_with_only_the_ipc_stamp_uses_it() -> None:
    line = "FLASER 2 1.0 1.0 0 0 0 0 0 0 42.5"
    (scan,) = parse_carmen_lines([line])
    assert scan.stamp == 42.5


# ---------------------------------------------------------------- no-returns


def test_readings_within_one_percent_of_the_log_maximum_are_no_returns(tmp_path: Path) -> None:
    # 81.91 is the SICK's "nothing seen"; 81.2 is within 1 % of it, 80.0 is not
    path = write_log(tmp_path, [flaser([3.0, 81.91, 81.2, 80.0]), flaser([81.91, 0.0, 2.5, 4.0])])
    first, second = read_carmen(path)
    assert first.range_max == second.range_max == pytest.approx(NO_RETURN_FRACTION * 81.91)
    assert first.ranges.tolist() == [3.0, math.inf, math.inf, 80.0]
    assert second.ranges.tolist() == [math.inf, 0.0, 2.5, 4.0]
    rays = second.to_rays()
    assert rays.skipped == 1  # the 0 (a dazzled beam) is skipped, not a hit at the sensor
    assert rays.hit.tolist() == [False, True, True]


def test_max_range_overrides_the_log_maximum(tmp_path: Path) -> None:
    path = write_log(tmp_path, [flaser([3.0, 39.7, 39.5, 81.91])])
    (scan,) = read_carmen(path, max_range=40.0)
    assert scan.range_max == pytest.approx(39.6)
    assert scan.ranges.tolist() == [3.0, math.inf, 39.5, math.inf]


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf])
def test_an_unusable_max_range_is_refused(tmp_path: Path, bad: float) -> None:
    path = write_log(tmp_path, [flaser([3.0, 4.0])])
    with pytest.raises(ValueError, match="max_range"):
        read_carmen(path, max_range=bad)


@pytest.mark.parametrize(("name", "maximum"), [("orebro-corrected.log.gz", 32.767),
                                               ("csail-corrected.log.gz", 81.91),
                                               ("fhw-corrected.log.gz", 51.1)])
def test_each_shared_log_has_its_own_scanner_maximum(name: str, maximum: float) -> None:
    path = carmen_log(name)
    with gzip.open(path, "rt") as lines:
        raw = np.concatenate([s.ranges for s in parse_carmen_lines(lines)])
    scans = read_carmen(path)
    assert raw.max() == maximum
    assert [s.range_max for s in scans] == pytest.approx([NO_RETURN_FRACTION * maximum] * len(scans))
    no_returns = sum(int(np.isinf(s.ranges).sum()) for s in scans)
    assert no_returns == int((raw >= NO_RETURN_FRACTION * maximum).sum()) > 0
    assert all(np.all(s.ranges[np.isfinite(s.ranges)] < s.range_max) for s in scans)


# ---------------------------------------------------------------- ROBOTLASER1


def test_robotlaser1_states_its_angles_range_and_laser_pose() -> None:
    (raw,) = parse_carmen_lines([robotlaser([1.0, 2.0, 29.8, 29.0])])
    assert raw.angle_min == -2.35619 and raw.angle_increment == 0.00436332
    assert raw.pose == (3.0, 4.0, 1.25)  # the laser's pose, not the robot's (2.9 3.9 1.2)
    assert raw.max_range == 30.0
    assert raw.stamp == 78.25  # the logger's stamp, after tv rv and the safety fields
    assert raw.ranges.tolist() == [1.0, 2.0, 29.8, 29.0]


def test_robotlaser1_no_returns_follow_the_stated_maximum(tmp_path: Path) -> None:
    path = write_log(tmp_path, [robotlaser([1.0, 29.8, 29.0], remissions=0)])
    (scan,) = read_carmen(path)
    assert scan.range_max == pytest.approx(29.7)
    assert scan.ranges.tolist() == [1.0, math.inf, 29.0]


# ---------------------------------------------------------------- what is skipped, what is refused


def test_other_messages_comments_and_blank_lines_are_skipped_and_lines_keep_their_numbers() -> None:
    lines = [
        "# message formats defined: PARAM SYNC ODOM FLASER RLASER",
        "PARAM robot_front_laser_max 81.9 nohost 0",
        "ODOM 0.1 0.2 0.3 0 0 0 12.0 pippo 12.0",
        "",
        flaser([1.0, 2.0]),
        "NEFF 87.4 pippo 12.3",
        "#PARAM laser_front_laser_resolution 1.0",
        "RAWLASER1 0 -1.5 3.1 0.01 81.9 0.01 0 2 1.0 2.0 0 5.0 host 5.0",
        robotlaser([3.0, 4.0]),
    ]
    scans = list(parse_carmen_lines(lines))
    assert [s.line for s in scans] == [5, 9]
    assert all(isinstance(s, CarmenScan) for s in scans)


@pytest.mark.parametrize(("line", "says"), [
    ("FLASER 4 1.0 2.0 3.0", "needs 4 values"),                  # cut short
    ("FLASER 3 1.0 2.x 3.0 0 0 0 0 0 0 1 h 1", "'2.x', not a number"),
    ("FLASER 3 1.0 nan 3.0 0 0 0 0 0 0 1 h 1", "not a finite number"),
    ("FLASER 180.5 1.0", "whole number"),
    ("FLASER 1 1.0 0 0 0 0 0 0 1 h 1", "whole number >= 2"),
    ("FLASER 2 1.0 2.0 0 0", "pose"),                              # the pose is cut short
    ("ROBOTLASER1 0 -1.5 3.1 0.01 81.9 0.01 0 3 1.0 2.0", "ROBOTLASER1 ranges"),
    ("ROBOTLASER1 0 -1.5 3.1 0.01 81.9 0.01 0 2 1.0 2.0 -1 0 0 0", "remission count"),
    ("ROBOTLASER1 0 -1.5 3.1 0.01 0 0.01 0 2 1.0 2.0 0 0 0 0", "maximum range"),
])
def test_a_malformed_scan_line_raises_naming_its_line(tmp_path: Path, line: str, says: str) -> None:
    path = write_log(tmp_path, ["ODOM 0 0 0 0 0 0 1 h 1", flaser([1.0, 2.0]), line, flaser([1.0, 2.0])])
    with pytest.raises(ValueError, match="line 3") as info:
        read_carmen(path)
    assert says in str(info.value) and str(path) in str(info.value)


def test_a_log_without_scans_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no FLASER or ROBOTLASER1"):
        read_carmen(write_log(tmp_path, ["ODOM 0 0 0 0 0 0 1 h 1"]))


def test_a_missing_log_raises_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_carmen(tmp_path / "nowhere.log.gz")


def test_a_truncated_gzip_log_is_refused_not_read_in_part(tmp_path: Path) -> None:
    whole = gzip.compress(("\n".join(flaser([1.0 + i % 7, 2.0] * 90) for i in range(200)) + "\n").encode())
    path = tmp_path / "cut.log.gz"
    path.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(ValueError, match="truncated or corrupt"):
        read_carmen(path)


def test_plain_and_gzip_logs_read_the_same(tmp_path: Path) -> None:
    lines = [flaser([1.0, 2.0, 81.91]), robotlaser([3.0, 4.0])]
    plain = read_carmen(write_log(tmp_path, lines))
    packed = tmp_path / "test.log.gz"
    packed.write_bytes(gzip.compress(("\n".join(lines) + "\n").encode()))
    for a, b in zip(plain, read_carmen(packed), strict=True):
        assert (a.pose, a.angle_min, a.angle_increment, a.range_max) == (b.pose, b.angle_min, b.angle_increment,
                                                                           b.range_max)
        assert a.ranges.tolist() == b.ranges.tolist()


# ---------------------------------------------------------------- the real logs of tests/data


@pytest.mark.parametrize("name", sorted(REAL_LOGS))
def test_every_shared_log_reads_with_the_scan_count_of_its_readme(name: str) -> None:
    count, beams = REAL_LOGS[name]
    scans = read_carmen(carmen_log(name))
    assert len(scans) == count
    assert {s.ranges.size for s in scans} == {beams}
    assert {s.angle_min for s in scans} == {-math.pi / 2}
    maximum = scans[0].range_max / NO_RETURN_FRACTION  # 32.767 m, about 51.1 m or 81.91 m
    assert any(abs(maximum - m) < 0.2 for m in (32.767, 51.1, 81.91)), maximum
    # the poses are a building's, in metres: a few hundred at most, and the robot moves
    poses = np.array([s.pose for s in scans])
    assert np.all(np.abs(poses[:, :2]) < 300.0) and np.ptp(poses[:, 0]) + np.ptp(poses[:, 1]) > 10.0


# ---------------------------------------------------------------- the grid of a log


def test_the_grid_holds_poses_and_hits_with_the_margin_and_ignores_no_returns(tmp_path: Path) -> None:
    # a robot at (10, 20) facing +x: a hit 3 m to its right, a no-return ahead, a hit 2 m to its left
    (scan,) = read_carmen(write_log(tmp_path, [flaser([3.0] + [81.91] * 179 + [2.0], pose=(10.0, 20.0, 0.0))]))
    spec = grid_for_scans([scan], resolution=0.1, margin=1.0)
    assert spec.origin == pytest.approx((9.0, 16.0))  # pose x - 1, hit y (17) - 1
    assert spec.upper == pytest.approx((11.0, 23.0))  # pose x + 1, hit y (22) + 1
    assert spec.shape == (20, 70)


def test_the_grid_of_a_real_log_holds_every_pose_and_hit_on_whole_cells() -> None:
    scans = read_carmen(carmen_log("orebro-corrected.log.gz"))
    spec = grid_for_scans(scans, resolution=0.05, margin=1.0)
    points = np.concatenate([np.array([s.pose[:2] for s in scans])]
                            + [r.endpoints[r.hit] for r in (s.to_rays() for s in scans)])
    lower, upper = np.array(spec.origin), np.array(spec.upper)
    assert np.all(points.min(axis=0) - 1.0 >= lower - 1e-9) and np.all(points.max(axis=0) + 1.0 <= upper + 1e-9)
    assert np.all(points.min(axis=0) - 1.0 < lower + 0.05)  # no more than a cell of extra padding
    assert np.all(np.abs(lower / 0.05 - np.round(lower / 0.05)) < 1e-6)  # origin on the 5 cm lattice


@pytest.mark.parametrize(("resolution", "margin", "says"), [(0.0, 1.0, "resolution"), (0.05, -1.0, "margin"),
                                                            (1e-4, 1.0, "cells")])
def test_an_unusable_grid_is_refused_with_what_to_change(resolution: float, margin: float, says: str) -> None:
    scans = read_carmen(carmen_log("orebro-corrected.log.gz"))
    with pytest.raises(ValueError, match=says):
        grid_for_scans(scans, resolution=resolution, margin=margin)


# ---------------------------------------------------------------- stamps


def _log_stamps(name: str) -> list[float]:
    with gzip.open(carmen_log(name), "rt") as lines:
        return [scan.stamp for scan in parse_carmen_lines(lines)]


#: The real logs whose stamps do not increase, and the stamp their numbering starts from, ns.
NUMBERED_LOGS = {
    "orebro-corrected.log.gz": 0,  # every stamp 0
    "belgioioso-corrected.log.gz": 1_018_930_000 * 10**9,  # one value
    "csail-corrected.log.gz": 1_134_860_000 * 10**9,  # two
    "infinite-corridor-corrected.log.gz": 0,  # from -0.445999 s, backwards: numbered from 0
}


@pytest.mark.parametrize("name", sorted(NUMBERED_LOGS))
def test_a_real_log_whose_stamps_do_not_increase_is_numbered_at_5_hz_from_its_first(name: str) -> None:
    raw = _log_stamps(name)
    assert any(b <= a for a, b in zip(raw, raw[1:]))  # what makes it one of them
    said: list[str] = []
    scans = read_carmen(carmen_log(name), say=said.append)
    assert [s.stamp_ns for s in scans] == [NUMBERED_LOGS[name] + k * 200_000_000 for k in range(len(scans))]
    assert log_stamps_ns(raw).numbered
    assert len(said) == 1 and name in said[0] and "numbered at 5 Hz" in said[0]


@pytest.mark.parametrize("name", sorted(set(REAL_LOGS) - set(NUMBERED_LOGS)))
def test_a_real_log_whose_stamps_increase_keeps_them_to_the_nanosecond(name: str) -> None:
    with gzip.open(carmen_log(name), "rt") as lines:
        # the logger's timestamp as written: the last field of each FLASER line
        written = [line.split()[-1] for line in lines if line.startswith("FLASER")]
    said: list[str] = []
    scans = read_carmen(carmen_log(name), say=said.append)
    for text, scan in zip(written, scans, strict=True):
        whole, _, fraction = text.partition(".")
        assert scan.stamp_ns == int(whole) * 10**9 + int(fraction.ljust(9, "0")), text
    assert said == []


@pytest.mark.parametrize(("stamps", "first"), [([3.0, 3.0], 3 * 10**9), ([2.0, 1.0], 2 * 10**9), ([-1.0, 0.5], 0),
                                               ([math.nan, 4.0], 0), ([1.0, math.inf], 10**9)])
def test_stamps_that_are_not_finite_non_negative_and_increasing_are_numbered(stamps: list[float], first: int) -> None:
    numbered = log_stamps_ns(stamps)
    assert numbered.numbered and numbered.ns == [first, first + 200_000_000]
    kept = log_stamps_ns([0.0, 0.25, 1018930000.15])
    assert not kept.numbered and kept.ns == [0, 250_000_000, 1_018_930_000_150_000_000]
