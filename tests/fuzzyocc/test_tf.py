"""fuzzyocc.tf: transforms between frames over time, against scipy's rotations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from fuzzyocc.tf import LookupFailed, Transform, TransformBuffer, slerp


def _close(t: Transform, position: np.ndarray, rotation: Rotation) -> bool:
    return bool(np.allclose(t.translation, position, atol=1e-12)
                and (Rotation.from_quat(t.rotation).inv() * rotation).magnitude() < 1e-12)


def test_slerp_is_scipys() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        pair = Rotation.random(2, random_state=rng)
        u = float(rng.uniform())
        ours = slerp(pair[0].as_quat(), pair[1].as_quat(), u)
        theirs = Slerp([0.0, 1.0], pair)([u])[0]
        assert (Rotation.from_quat(ours).inv() * theirs).magnitude() < 1e-12
    same = Rotation.from_euler("z", 0.3).as_quat()
    assert np.allclose(slerp(same, same, 0.5), same)
    assert np.allclose(slerp(same, -same, 0.5), same)  # q and -q: no turn at all


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
