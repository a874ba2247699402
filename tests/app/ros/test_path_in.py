"""A nav_msgs/Path in: its poses as a path's points in each state space's layout, and its frames held to the map's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.errors import Invalid
from app.ros.messages_out import path_message, yaw_quaternion
from app.ros.path_in import check_frames, path_points, yaw_of
from app.schemas import Header, PoseStamped, Quaternion


def _poses(points: list[list[float]], state_space: str, frame_id: str = "map") -> list[PoseStamped]:
    message = path_message(points, state_space=state_space, frame_id=frame_id, stamp={"sec": 1, "nanosec": 2})
    return [PoseStamped.model_validate(p) for p in message["poses"]]


@pytest.mark.parametrize("yaw", [0.0, 0.5, -2.0, math.pi - 1e-9, -math.pi / 2])
def test_the_yaw_of_an_orientation_is_the_one_it_was_made_of_whatever_its_norm(yaw: float) -> None:
    q = yaw_quaternion(yaw)
    assert yaw_of(Quaternion(**q)) == pytest.approx(yaw, abs=1e-12)
    assert yaw_of(Quaternion(**{k: 3.0 * v for k, v in q.items()})) == pytest.approx(yaw, abs=1e-12)


def test_poses_become_the_points_a_plan_request_takes() -> None:
    se2 = [[0.5, 1.0, 0.25], [1.5, 1.0, -1.0]]
    assert np.allclose(path_points(_poses(se2, "SE2"), "Dubins"), se2, atol=1e-12)
    r3 = [[0.5, 1.0, 2.0], [1.5, 1.0, 2.5]]
    assert path_points(_poses(r3, "R3"), "R3").tolist() == r3
    assert path_points(_poses(r3, "R3"), "R2").tolist() == [[0.5, 1.0], [1.5, 1.0]]  # z left out on a plane


@pytest.mark.parametrize("state_space", ["R2", "SE2", "R3"])
def test_a_plan_without_a_path_is_a_path_without_poses(state_space: str) -> None:
    """A plan that found nothing (status none) answers an empty nav_msgs/Path in every state space."""
    message = path_message([], state_space=state_space, frame_id="map", stamp={"sec": 1, "nanosec": 2})
    assert message["poses"] == [] and message["header"]["frame_id"] == "map"


def test_a_frame_other_than_the_maps_is_refused_naming_its_header() -> None:
    poses = _poses([[0.0, 0.0], [1.0, 0.0]], "R2")
    check_frames("map", Header(stamp={"sec": 0, "nanosec": 0}, frame_id=""), poses)  # empty: the path's frame
    with pytest.raises(Invalid, match=r"poses\[0\]\.header\.frame_id 'map' is not the map's frame 'robot1/map'"):
        check_frames("robot1/map", None, poses)
    with pytest.raises(Invalid, match=r"^header\.frame_id 'odom'"):
        check_frames("map", Header(stamp={"sec": 0, "nanosec": 0}, frame_id="odom"), poses)
