"""What a plan returns (``PlanResult``, and its JSON form), how an unusable start or goal is refused, and what a
path check returns (``PathCheck``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np

Status = Literal["exact", "approximate", "none"]
StoppedBy = Literal["complete", "solution", "iterations", "time_limit"]

# Nav2's ComputePathToPose error names (nav2_msgs/action/ComputePathToPose.action)
START_OUTSIDE_MAP = "START_OUTSIDE_MAP"
GOAL_OUTSIDE_MAP = "GOAL_OUTSIDE_MAP"
START_OCCUPIED = "START_OCCUPIED"
GOAL_OCCUPIED = "GOAL_OCCUPIED"
PLAN_ERROR_CODES = (START_OUTSIDE_MAP, GOAL_OUTSIDE_MAP, START_OCCUPIED, GOAL_OCCUPIED)
# ... and those of a plan that ran but did not reach the goal (PlanResult.error_code)
TIMEOUT = "TIMEOUT"
NO_VALID_PATH = "NO_VALID_PATH"
RESULT_ERROR_CODES = (TIMEOUT, NO_VALID_PATH)


class PlanError(Exception):
    """A start or goal the planner cannot use, raised before any planner runs.

    Parameters
    ----------
    code : str
        One of Nav2's names: START_OUTSIDE_MAP, GOAL_OUTSIDE_MAP, START_OCCUPIED,
        GOAL_OCCUPIED. A start or goal in never-observed space while ``allow_unknown`` is
        false is reported as *_OCCUPIED (Nav2 has no separate code), with a message that
        says the space is unknown.
    message : str
        What is wrong, with the numbers; ``str(error)`` is this message.
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(code, message)  # both in args, so the error pickles across processes
        self.code = code
        self.message = message

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class PlanResult:
    """A planned path and its measures, all against the field dilated by the robot radius.

    Attributes
    ----------
    status : "exact" | "approximate" | "none"
        "exact": the path ends within ``goal_tolerance`` of the goal. "approximate": the
        planner got only part of the way; the path ends at the state nearest the goal it
        reached. "none": no path (``message`` says why); ``path`` is empty and the measures
        are NaN.
    path : (K, 2) | (K, 3) float64 array
        x, y (R2); x, y, theta (SE2, Dubins, ReedsShepp); x, y, z (R3). Interpolated at
        the map resolution (no two consecutive states further apart than one cell).
    length : float
        Length of the path's position trace, metres.
    max_risk : float
        Largest dilated risk along the path: at most the ``max_risk`` asked for where the footprint
        covers observed cells only; never-observed cells count 0.5 (``allow_unknown`` bounds them).
    mean_risk : float
        Risk integral divided by the length (the dilated risk at the start for a
        zero-length path).
    cost : float
        ``length + risk_weight * integral of dilated risk along the path`` (metres x risk).
    planner, state_space : str
        What planned.
    planning_time : float
        Wall time of the whole ``plan`` call, seconds.
    message : str
        Empty, or why the status is not "exact".
    iterations : int
        Planner iterations where the planner counts them (RRT family, BIT*), else 0.
    first_solution_time : float
        Seconds from the start of ``plan`` until the planner first held a path to the goal
        region (or its approximation); NaN when status is "none".
    error_code : str
        Empty when status is "exact"; otherwise Nav2's ComputePathToPose name for why not:
        "TIMEOUT" (a sampling planner's time limit, or a seeded plan's iteration budget, ended
        the search before it reached the goal) or "NO_VALID_PATH" (the grid planner's complete search found none, or no
        candidate path passed verification).
    stopped_by : "complete" | "solution" | "iterations" | "time_limit"
        What ended the search: the grid planner's search ran to its end ("complete"); a
        planner that stops at its first solution found one ("solution"); the iteration budget
        (a seeded plan's, or ``max_iterations``) ran out ("iterations"); the clock did
        ("time_limit": for a seeded plan, the path may differ between runs).
    """

    status: Status
    path: np.ndarray
    length: float
    max_risk: float
    mean_risk: float
    cost: float
    planner: str
    state_space: str
    planning_time: float
    message: str = ""
    iterations: int = 0
    first_solution_time: float = float("nan")
    error_code: str = ""
    stopped_by: StoppedBy = "complete"

    def to_json(self) -> dict[str, Any]:
        """This result as plain JSON data, every field by its name in the dataclass's order.

        ``path`` as a list of states (lists of floats); a NaN measure (no path, no first solution) as
        None, since JSON has no NaN; an empty ``error_code`` (exact) as None; numpy scalars as Python
        numbers. Plain data crosses a process boundary and is the body of the service's answer.
        """
        plain = {f.name: _json_value(getattr(self, f.name)) for f in fields(self)}
        plain["error_code"] = self.error_code or None
        return plain


def _json_value(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.astype(np.float64, copy=False).tolist()
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, int | np.integer):
        return int(value)
    return str(value)


@dataclass(frozen=True)
class PathCheck:
    """A given path held to a plan's rules and measured as a plan measures its own (``planning.check_path``).

    Attributes
    ----------
    valid : bool
        Every cell every segment crosses is valid, and every point lies on the map.
    first_invalid_index : int or None
        The first point whose segment to the next is invalid (a segment with an end off the map
        included), or the point itself when the path is that one point; None when valid.
    max_risk, cost, length : float or None
        Over the whole path, as ``PlanResult``'s: the largest dilated risk met, ``length +
        risk_weight * integral of dilated risk``, and the length in metres; None when a point lies
        off the map, where the field holds no risk.
    """

    valid: bool
    first_invalid_index: int | None
    max_risk: float | None
    cost: float | None
    length: float | None
