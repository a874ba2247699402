"""check_path(): the planner's dense check of a given path, bit for bit, on the window the path reaches."""

from __future__ import annotations

import numpy as np
import pytest

from planning import RiskField, check_path, plan
from planning.packed import PackedGrid
from planning.path_check import MAX_WALK_CELLS, PathTooLong

RES = 0.05


def _random_case(rng: np.random.Generator, ndim: int) -> tuple[RiskField, np.ndarray, dict[str, object]]:
    shape = tuple(int(n) for n in rng.integers(5, 40, ndim))
    res = float(rng.choice([0.05, 0.07, 0.1, 0.3]))
    origin = tuple(float(v) for v in rng.uniform(-5, 5, ndim).round(2))
    risk = rng.uniform(0, 1, shape).astype(np.float32) ** 3
    field = RiskField(risk, res, origin, observed=rng.uniform(size=shape) > 0.2)
    rules = {
        "robot_radius": min(float(rng.choice([0.0, 0.05, 0.1, 0.33, 1.0])), 0.4 * min(shape) * res),
        "max_risk": float(rng.uniform(0.2, 1.0)),
        "risk_weight": float(rng.uniform(0.0, 5.0)),
        "allow_unknown": bool(rng.integers(2)),
    }
    low = np.asarray(origin)
    high = low + np.asarray(shape) * res
    count = int(rng.integers(1, 12))
    kind = int(rng.integers(3))
    if kind == 0:  # anywhere, a tenth of the map beyond each edge included
        points = rng.uniform(low - 0.1 * (high - low), high + 0.1 * (high - low), (count, ndim))
    elif kind == 1:  # on cell boundaries and corners, where rounding decides the cell
        points = low + rng.integers(0, np.asarray(shape) + 1, (count, ndim)) * res
    else:  # a short local path well inside: a window smaller than the map
        centre = rng.uniform(low + 0.3 * (high - low), high - 0.3 * (high - low))
        points = centre + rng.normal(0.0, 2 * res, (count, ndim))
    return field, points, rules


@pytest.mark.parametrize("ndim", [2, 3])
def test_the_check_is_the_planners_dense_check_of_the_whole_field_bit_for_bit(ndim: int) -> None:
    rng = np.random.default_rng(ndim)
    for _ in range(400):
        field, points, rules = _random_case(rng, ndim)
        whole = PackedGrid(field, rules["robot_radius"], rules["max_risk"], rules["allow_unknown"],  # type: ignore[arg-type]
                           rules["risk_weight"]).evaluate(points)  # type: ignore[arg-type]
        checked = check_path(field, points.tolist(), **rules)  # type: ignore[arg-type]
        assert checked.valid == whole.valid
        assert checked.first_invalid_index == (None if whole.valid else whole.first_bad_segment)
        cells = (points - np.asarray(field.origin)) * (1.0 / field.resolution)  # as the kernels place a point
        if ((cells >= 0) & (cells < np.asarray(field.shape))).all():
            assert (checked.length, checked.max_risk) == (whole.length, whole.peak)
            assert checked.cost == whole.length + rules["risk_weight"] * whole.integral  # type: ignore[operator]
        else:
            assert not checked.valid and checked.length is checked.cost is checked.max_risk is None


@pytest.fixture(scope="module")
def hall() -> RiskField:
    """4 x 4 m at 0.05 m: a wall at x = 2.0-2.1 m with a door at y = 1.5-2.5 m, never-observed cells at y > 3.5 m."""
    risk = np.zeros((80, 80), np.float32)
    risk[40:42, :] = 1.0
    risk[40:42, 30:50] = 0.0
    observed = np.ones((80, 80), bool)
    observed[:, 70:] = False
    risk[:, 70:] = 0.5
    return RiskField(risk, RES, (0.0, 0.0), observed=observed)


@pytest.mark.parametrize(("planner", "state_space", "extra"), [
    ("grid", "R2", {}),
    ("RRTConnect", "R2", {}),
    ("RRTstar", "SE2", {}),
    ("RRTConnect", "Dubins", {"turning_radius": 0.3}),
])
def test_a_path_the_planner_returned_is_valid_and_costs_what_the_plan_said(
        hall: RiskField, planner: str, state_space: str, extra: dict[str, float]) -> None:
    z = [0.0] if state_space != "R2" else []
    rules = {"robot_radius": 0.15, "max_risk": 0.45, "risk_weight": 2.0, "allow_unknown": False}
    result = plan(hall, [0.5, 0.5, *z], [3.5, 3.0, *z], planner=planner, state_space=state_space, seed=4,
                  time_limit=2.0, **rules, **extra)  # type: ignore[arg-type]
    assert result.status == "exact"
    checked = check_path(hall, result.path.tolist(), state_space=state_space, **rules)  # type: ignore[arg-type]
    assert checked.valid and checked.first_invalid_index is None
    if state_space == "Dubins":  # the plan measured its curve as quarter-cell chords, the path has a point a cell
        assert checked.length == pytest.approx(result.length, rel=1e-3)
        assert checked.cost == pytest.approx(result.cost, rel=1e-3)
    else:
        assert (checked.length, checked.cost, checked.max_risk) == (result.length, result.cost, result.max_risk)
    # held to a tighter rule, the same path no longer passes where it crosses the door's footprint
    assert not check_path(hall, result.path.tolist(), state_space=state_space, robot_radius=0.6).valid


def test_a_path_the_planner_returned_in_3d_is_valid() -> None:
    risk = np.zeros((40, 40, 10), np.float32)
    risk[20, :, :] = 1.0
    risk[20, 15:25, 2:8] = 0.0  # a window in the wall
    field = RiskField(risk, 0.1, (0.0, 0.0, 0.0))
    result = plan(field, (0.5, 2.0, 0.5), (3.5, 2.0, 0.5), planner="grid", robot_radius=0.05)
    assert result.status == "exact"
    checked = check_path(field, result.path.tolist(), robot_radius=0.05)
    assert checked.valid and (checked.cost, checked.length) == (result.cost, result.length)
    straight = check_path(field, [[0.5, 1.0, 0.5], [3.5, 1.0, 0.5]], robot_radius=0.05)  # below the window
    assert not straight.valid and straight.first_invalid_index == 0 and straight.max_risk == 1.0


def test_the_first_invalid_index_is_the_point_whose_segment_crosses_the_wall(hall: RiskField) -> None:
    path = [[0.5, 1.0], [1.5, 1.0], [2.5, 1.0], [3.5, 1.0]]  # the wall at x = 2.0-2.1 m, below the door
    checked = check_path(hall, path, robot_radius=0.1)
    assert not checked.valid and checked.first_invalid_index == 1
    assert checked.max_risk == 1.0 and checked.length == pytest.approx(3.0)
    through_door = [[0.5, 2.0], [3.5, 2.0]]
    assert check_path(hall, through_door, robot_radius=0.1).valid
    assert check_path(hall, [[2.05, 1.0]], robot_radius=0.0).first_invalid_index == 0  # one point, in the wall


def test_unknown_space_is_invalid_only_without_allow_unknown(hall: RiskField) -> None:
    path = [[0.5, 3.0], [0.5, 3.8], [1.0, 3.8]]  # into the never-observed band y > 3.5 m
    allowed = check_path(hall, path, robot_radius=0.1, allow_unknown=True)
    refused = check_path(hall, path, robot_radius=0.1, allow_unknown=False)
    assert allowed.valid and allowed.max_risk == 0.5
    assert not refused.valid and refused.first_invalid_index == 0
    # risk 0.5 counts against max_risk only where it was observed
    assert check_path(hall, path, robot_radius=0.1, max_risk=0.1).valid


def test_a_point_off_the_map_makes_its_segment_invalid_and_the_path_unmeasured(hall: RiskField) -> None:
    checked = check_path(hall, [[0.5, 0.5], [1.0, 0.5], [1.0, -0.5], [1.5, 0.5]], robot_radius=0.1)
    assert not checked.valid and checked.first_invalid_index == 1
    assert checked.length is None and checked.cost is None and checked.max_risk is None
    far = check_path(hall, [[1e300, 0.5], [-1e300, 2.0]])  # no overflow, no walk
    assert not far.valid and far.first_invalid_index == 0
    assert check_path(hall, [[4.0, 1.0]]).first_invalid_index == 0  # the map's upper edge is not on it


def test_arguments_are_checked_as_a_plans_and_named(hall: RiskField) -> None:
    with pytest.raises(ValueError, match=r"path\[1\]: R2 needs \(x, y\)"):
        check_path(hall, [[0.5, 0.5], [1.0, 0.5, 0.0]])
    with pytest.raises(ValueError, match=r"path\[0\]: SE2 needs \(x, y, theta\)"):
        check_path(hall, [[0.5, 0.5]], state_space="SE2")
    with pytest.raises(ValueError, match=r"path\[1\]: must be finite"):
        check_path(hall, [[0.5, 0.5], [float("nan"), 0.5]])
    with pytest.raises(ValueError, match="path: needs at least one point"):
        check_path(hall, [])
    with pytest.raises(ValueError, match="state_space: R3 needs a 3-D field"):
        check_path(hall, [[0.5, 0.5, 0.5]], state_space="R3")
    with pytest.raises(ValueError, match="robot_radius: must be a finite number >= 0.0 and <= 2.8"):
        check_path(hall, [[0.5, 0.5]], robot_radius=3.0)
    with pytest.raises(ValueError, match="max_risk"):
        check_path(hall, [[0.5, 0.5]], max_risk=1.5)
    with pytest.raises(ValueError, match="risk_weight"):
        check_path(hall, [[0.5, 0.5]], risk_weight=1e5)


def test_a_path_crossing_too_many_cells_is_refused_before_the_walk() -> None:
    field = RiskField(np.zeros((2000, 2000), np.float32), RES, (0.0, 0.0))
    # each segment crosses the map, about 2,000 cells
    zigzag = [[0.1 + 99.8 * (k % 2), 0.1 + k * 0.01] for k in range(MAX_WALK_CELLS // 1900)]
    with pytest.raises(PathTooLong, match="check it in parts"):
        check_path(field, zigzag)
    assert check_path(field, zigzag[:100]).valid  # the same segments, fewer of them
