"""app.maps.correction: a corrected trajectory's poses given to the scans of a stored history."""

from __future__ import annotations

import numpy as np
import pytest

from app.maps import correction, logcodec
from app.storage import StoredMap
from fuzzyocc import LaserScan, PointCloud
from fuzzyocc.trajectory import Trajectory


def _laser(x: float, stamp: int | None) -> LaserScan:
    return LaserScan(pose=(x, 0.0, 0.0), angle_min=-0.5, angle_increment=0.5, ranges=np.array([2.0, 2.0, 2.0]), range_min=0.1,
                     range_max=10.0, stamp_ns=stamp)


def _history(*batches: list[LaserScan | PointCloud]) -> StoredMap:
    return StoredMap("m", {}, "t", batches=[(v + 1, logcodec.encode(b)) for v, b in enumerate(batches)])


TRAJECTORY = Trajectory([10, 20, 30], [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], [[0.0, 0.0, 0.0, 1.0]] * 3)


def test_scans_in_range_take_the_interpolated_pose_and_the_others_keep_theirs() -> None:
    history = _history([_laser(5.0, 15), _laser(5.0, 40)], [_laser(5.0, None), _laser(5.0, 30)])
    planned = correction.plan(history, TRAJECTORY, through=2)
    assert planned.scans == 2 and sorted(planned.moves) == [1, 2]
    assert planned.moves[1][0, :3].tolist() == [0.5, 0.0, 0.0] and np.isnan(planned.moves[1][1]).all()
    assert np.isnan(planned.moves[2][0]).all() and planned.moves[2][1, :3].tolist() == [2.0, 0.0, 0.0]
    back = correction.decode(correction.encode(planned))
    assert back.through == 2 and back.scans == 2
    assert all(np.array_equal(back.moves[v], planned.moves[v], equal_nan=True) for v in planned.moves)
    # a batch after ``through`` keeps its poses
    assert correction.plan(history, TRAJECTORY, through=1).scans == 1


def test_a_cloud_stored_in_the_map_frame_cannot_be_reposed_and_nothing_in_range_is_a_conflict() -> None:
    placed = PointCloud(points=np.array([[1.0, 1.0, 1.0]]), origin=(0.0, 0.0, 1.0), range_max=5.0, stamp_ns=20)
    with pytest.raises(correction.CannotRepose, match="stored in the map frame"):
        correction.plan(_history([placed]), TRAJECTORY, through=1)
    with pytest.raises(correction.NothingToCorrect, match="scans stamped 50 to 60 ns"):
        correction.plan(_history([_laser(0.0, 50), _laser(0.0, 60)]), TRAJECTORY, through=1)
