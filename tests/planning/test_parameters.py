"""planning.parameters: each number's range, checked with the message ``plan`` gives."""

from __future__ import annotations

import math

import pytest

from planning.parameters import MAX_RISK, ROBOT_RADIUS, TIME_LIMIT, Number


@pytest.mark.parametrize(
    ("number", "value", "high", "message"),
    [
        (TIME_LIMIT, 0, math.inf, "time_limit: must be a finite number > 0.0, got 0"),
        (MAX_RISK, 1.5, math.inf, "max_risk: must be a finite number >= 0.0 and <= 1.0, got 1.5"),
        (MAX_RISK, 0.9, 0.5, "max_risk: must be a finite number >= 0.0 and <= 0.5, got 0.9"),
        (ROBOT_RADIUS, 2.0, 1.0, "robot_radius: must be a finite number >= 0.0 and <= 1.0, got 2.0"),
        (ROBOT_RADIUS, float("nan"), math.inf, "robot_radius: must be a finite number >= 0.0, got nan"),
        (ROBOT_RADIUS, "wide", math.inf, "robot_radius: must be a number, got 'wide'"),
    ],
)
def test_a_number_out_of_its_range_is_refused_by_name(number: Number, value: object, high: float, message: str) -> None:
    with pytest.raises(ValueError) as error:
        number.check(value, high=high)
    assert str(error.value) == message


def test_a_number_in_its_range_comes_back_as_a_float() -> None:
    assert TIME_LIMIT.check("2") == 2.0 and MAX_RISK.check(1) == 1.0 and ROBOT_RADIUS.check(0) == 0.0
