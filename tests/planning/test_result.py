"""PlanResult.to_json: the one plain form of a plan's result, which the service answers with."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from planning import PlanResult


def test_a_result_without_a_path_has_null_measures_and_an_empty_path() -> None:
    nan = math.nan
    result = PlanResult("none", np.zeros((0, 3)), nan, nan, nan, nan, "RRTstar", "SE2", 0.25,
                        "no path", 0, nan, "TIMEOUT", "time_limit")  # fmt: skip
    plain = result.to_json()
    assert list(plain) == [f.name for f in dataclasses.fields(PlanResult)]
    assert plain["path"] == [] and plain["length"] is None and plain["cost"] is None
    assert plain["first_solution_time"] is None and plain["error_code"] == "TIMEOUT"
    json.dumps(plain, allow_nan=False)


def test_an_exact_result_has_no_error_code_and_plain_numbers() -> None:
    path = np.array([[0.0, 0.0], [0.05, 0.0]], dtype=np.float64)
    result = PlanResult("exact", path, np.float64(0.05), np.float32(0.25), 0.1, 0.06, "grid", "R2",
                        np.float64(0.01), iterations=np.int64(7), first_solution_time=0.005)  # fmt: skip
    plain = result.to_json()
    assert plain["path"] == [[0.0, 0.0], [0.05, 0.0]] and plain["error_code"] is None and plain["message"] == ""
    assert type(plain["length"]) is float and type(plain["iterations"]) is int and plain["iterations"] == 7
    assert plain["max_risk"] == 0.25 and plain["stopped_by"] == "complete"
    json.dumps(plain, allow_nan=False)
