import dataclasses
import math

import numpy as np
import pytest

from fuzzyocc.membership import (
    LeftShoulder,
    RightShoulder,
    Trapezoid,
    Triangle,
    check_coverage,
    coverage_gaps,
    ladder,
)


def test_triangle_is_linear_on_each_side_and_zero_outside() -> None:
    tri = Triangle(-1.0, 0.0, 1.5)
    x = np.array([[-2.0, -1.0, -0.5], [0.0, 0.75, 3.0]])
    np.testing.assert_allclose(tri(x), [[0.0, 0.0, 0.5], [1.0, 0.5, 0.0]])
    assert tri(x).shape == (2, 3)


def test_shoulders_are_constant_beyond_their_ramp_including_infinity() -> None:
    left, right = LeftShoulder(-5.0, -4.0), RightShoulder(0.0, 1.5)
    x = np.array([-np.inf, -5.0, -4.5, -4.0, 0.0, 0.75, 1.5, np.inf])
    np.testing.assert_allclose(left(x), [1, 1, 0.5, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(right(x), [0, 0, 0, 0, 0, 0.5, 1, 1])


def test_trapezoid_has_a_plateau_and_degenerates_to_a_triangle() -> None:
    np.testing.assert_allclose(Trapezoid(0.0, 1.0, 2.0, 4.0)([0.5, 1.5, 3.0, 5.0]), [0.5, 1.0, 0.5, 0.0])
    np.testing.assert_allclose(Trapezoid(0.0, 1.0, 1.0, 2.0)([0.5, 1.0, 1.5]), Triangle(0.0, 1.0, 2.0)([0.5, 1.0, 1.5]))


def test_nan_input_stays_nan() -> None:
    assert math.isnan(float(Triangle(0.0, 1.0, 2.0)(np.nan)))


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: Triangle(0.0, 0.0, 1.0), "peak"),
        (lambda: Triangle(0.0, 2.0, 1.0), "right"),
        (lambda: LeftShoulder(1.0, 1.0), "zero_at"),
        (lambda: RightShoulder(2.0, 1.0), "top_start"),
        (lambda: Trapezoid(0.0, 2.0, 1.0, 3.0), "c"),
        (lambda: Triangle(0.0, math.nan, 1.0), "peak"),
        (lambda: LeftShoulder(-math.inf, 0.0), "top_end"),
    ],
)
def test_bad_parameters_are_refused_naming_the_field(make, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        make()


def test_membership_functions_are_frozen() -> None:
    tri = Triangle(0.0, 1.0, 2.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        tri.peak = 0.5  # type: ignore[misc]


def test_ladder_is_a_partition_of_unity_with_at_most_two_active() -> None:
    mfs = ladder([-5.0, -4.0, -3.0, -2.0, -1.0, 0.0, 1.5])
    x = np.random.default_rng(0).uniform(-10.0, 5.0, 10_000)
    values = np.stack([mf(x) for mf in mfs])
    np.testing.assert_allclose(values.sum(axis=0), 1.0, atol=1e-12)
    assert (values > 0).sum(axis=0).max() <= 2
    assert isinstance(mfs[0], LeftShoulder) and isinstance(mfs[-1], RightShoulder)


def test_ladder_needs_increasing_peaks() -> None:
    with pytest.raises(ValueError, match=r"peaks\[1\]"):
        ladder([0.0, 0.0, 1.0])


def test_supports_are_the_open_intervals_where_membership_is_positive() -> None:
    assert Triangle(-1.0, 0.0, 1.5).support == (-1.0, 1.5)
    assert LeftShoulder(-5.0, -4.0).support == (-math.inf, -4.0)
    assert RightShoulder(0.0, 1.5).support == (0.0, math.inf)


def test_coverage_of_the_real_line_by_a_ladder() -> None:
    assert coverage_gaps(ladder([-2.0, 0.0, 2.0])) == []


def test_touching_supports_leave_the_touching_point_uncovered() -> None:
    # The left shoulder is 0 at 0 and the right one too: x = 0 has no membership.
    assert coverage_gaps([LeftShoulder(-1.0, 0.0), RightShoulder(0.0, 1.0)]) == [(0.0, 0.0)]


def test_missing_shoulders_leave_the_infinite_ends_uncovered() -> None:
    gaps = coverage_gaps([Triangle(-1.0, 0.0, 1.0)])
    assert gaps == [(-math.inf, -1.0), (1.0, math.inf)]


def test_gaps_are_reported_within_a_bounded_axis_only() -> None:
    mfs = [Triangle(0.2, 0.3, 0.5), Triangle(0.6, 0.7, 0.8)]
    assert coverage_gaps(mfs, 0.0, 1.0) == [(0.0, 0.2), (0.5, 0.6), (0.8, 1.0)]
    # Functions reaching past the axis cover its ends.
    assert coverage_gaps([LeftShoulder(0.0, 0.6), RightShoulder(0.4, 1.0)], 0.0, 1.0) == []


def test_check_coverage_says_exactly_where_the_axis_is_uncovered() -> None:
    mfs = [LeftShoulder(-1.0, 0.0), Triangle(0.5, 1.0, 2.0), RightShoulder(2.0, 3.0)]
    with pytest.raises(ValueError, match=r"input MFs .*\[0, 0.5\], x = 2"):
        check_coverage(mfs, -math.inf, math.inf, "input MFs")
    check_coverage(ladder([0.0, 1.0]), -math.inf, math.inf, "fine")  # no exception
