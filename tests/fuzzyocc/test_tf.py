"""fuzzyocc.tf: transforms between frames over time, interpolated and chained as tf2 does."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from fuzzyocc.tf import LookupFailed, Transform, TransformBuffer


def _close(t: Transform, position: np.ndarray, rotation: Rotation) -> bool:
    return bool(np.allclose(t.translation, position, atol=1e-12)
                and (t.rotation.inv() * rotation).magnitude() < 1e-12)


def test_a_rotation_between_two_samples_is_interpolated_the_shorter_way_round() -> None:
    buffer = TransformBuffer()
    buffer.add("map", "odom", 0, Transform.of([0, 0, 0], Rotation.from_euler("z", 0.1).as_quat()))
    buffer.add("map", "odom", 100, Transform.of([1, 0, 0], Rotation.from_euler("z", 0.5).as_quat()))
    # -q is the same rotation as q: the way from 0.5 to 3.0 rad is 2.5 rad forwards, not through -q's side
    buffer.add("map", "odom", 200, Transform.of([1, 2, 0], -Rotation.from_euler("z", 3.0).as_quat()))
    # and from 3.0 to -3.0 rad the shorter way is 0.28 rad forwards, over pi, not 6 rad back
    buffer.add("map", "odom", 300, Transform.of([1, 2, 0], Rotation.from_euler("z", -3.0).as_quat()))
    assert _close(buffer.lookup("map", "odom", 25), np.array([0.25, 0, 0]), Rotation.from_euler("z", 0.2))
    assert _close(buffer.lookup("map", "odom", 160), np.array([1, 1.2, 0]), Rotation.from_euler("z", 0.5 + 0.6 * 2.5))
    assert _close(buffer.lookup("map", "odom", 250), np.array([1, 2, 0]), Rotation.from_euler("z", np.pi))
    same = buffer.lookup("map", "odom", 100)  # at a sample: that sample
    assert _close(same, np.array([1, 0, 0]), Rotation.from_euler("z", 0.5))


def test_stamps_since_the_epoch_interpolate_to_the_nanosecond() -> None:
    # 1.7e18 ns is past float64's exact integers (2**53): stamps are taken from the track's first sample
    t0 = 1_700_000_000 * 10**9
    buffer = TransformBuffer()
    buffer.add("odom", "base_link", t0, Transform.of([0, 0, 0], [0, 0, 0, 1]))
    buffer.add("odom", "base_link", t0 + 20_000_000, Transform.of([2, 0, 0], Rotation.from_euler("z", 1.0).as_quat()))
    u = 7_777_777 / 20_000_000
    assert _close(buffer.lookup("odom", "base_link", t0 + 7_777_777), np.array([2 * u, 0, 0]),
                  Rotation.from_euler("z", u))


def _buffer() -> TransformBuffer:
    buffer = TransformBuffer()
    for k, stamp in enumerate((0, 100, 200)):
        buffer.add("map", "odom", stamp, Transform.of([k, 0, 0], Rotation.from_euler("z", 0.1 * k).as_quat()))
    for k, stamp in enumerate(range(0, 201, 20)):
        buffer.add("/odom", "/base_link", stamp, Transform.of([0, 0.1 * k, 0], Rotation.from_euler("z", 0.3 * k)
                                                              .as_quat()))
    buffer.add("base_link", "laser", 0, Transform.of([0.2, 0, 0.3], Rotation.from_euler("x", np.pi).as_quat()),
               static=True)
    return buffer


def test_a_chain_is_interpolated_and_composed() -> None:
    buffer = _buffer()
    stamp = 137
    p1 = np.array([1.37, 0, 0])
    r1 = Rotation.from_euler("z", 0.137)
    p2 = np.array([0, 0.1 * 6.85, 0])
    r2 = Slerp([120.0, 140.0], Rotation.from_euler("z", [[1.8], [2.1]]))([137.0])[0]
    p3, r3 = np.array([0.2, 0, 0.3]), Rotation.from_euler("x", np.pi)
    position = p1 + r1.apply(p2 + r2.apply(p3))
    assert _close(buffer.lookup("map", "laser", stamp), position, r1 * r2 * r3)
    # the other way round, and between two branches of the tree
    assert _close(buffer.lookup("laser", "map", stamp), -(r1 * r2 * r3).inv().apply(position), (r1 * r2 * r3).inv())
    back = buffer.lookup("laser", "odom", stamp)
    assert _close(back, -(r2 * r3).inv().apply(p2 + r2.apply(p3)), (r2 * r3).inv())


def test_a_stamp_outside_the_samples_fails_with_a_countable_reason() -> None:
    buffer = _buffer()
    with pytest.raises(LookupFailed) as early:
        buffer.lookup("map", "laser", -1)
    assert early.value.reason == "before the first transform map -> odom"
    with pytest.raises(LookupFailed) as late:
        buffer.lookup("map", "laser", 201)
    assert late.value.reason == "after the last transform map -> odom"
    assert _close(buffer.lookup("map", "odom", 200), np.array([2.0, 0, 0]), Rotation.from_euler("z", 0.2))
    with pytest.raises(LookupFailed, match="no chain of transforms from camera to map"):
        buffer.lookup("map", "camera", 100)


def test_one_parent_per_frame_and_cycles_are_caught() -> None:
    buffer = _buffer()
    buffer.add("world", "odom", 50, Transform.identity())
    assert buffer.ignored == 1  # odom already hangs under map
    loop = TransformBuffer()
    loop.add("a", "b", 0, Transform.identity(), static=True)
    loop.add("b", "a", 0, Transform.identity(), static=True)
    with pytest.raises(LookupFailed, match="cycle"):
        loop.lookup("c", "a", 0)


def test_bad_numbers_are_refused() -> None:
    with pytest.raises(ValueError):
        Transform.of([0, 0, np.nan], [0, 0, 0, 1])
    with pytest.raises(ValueError):
        Transform.of([0, 0, 0], [0, 0, 0, 0])
