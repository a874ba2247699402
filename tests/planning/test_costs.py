"""One cost definition for every planner: length + risk_weight * integral of dilated risk."""

from __future__ import annotations

import numpy as np
import pytest

from planning import RiskField, plan

RES = 0.05


@pytest.mark.parametrize("planner", ["grid", "RRTConnect", "RRTstar", "BITstar"])
def test_straight_path_on_uniform_risk_costs_length_times_one_plus_weighted_risk(planner: str) -> None:
    # uniform risk 0.25, weight 2: the straight line is optimal and costs 5 * (1 + 2 * 0.25)
    field = RiskField(np.full((140, 60), 0.25, np.float32), RES, (0.0, 0.0))
    start, goal = (1.025, 1.525), (6.025, 1.525)
    # a generous limit: the seeded plan ends by its iteration count, and a loaded machine's clock
    # must not cut the simplification that straightens the path
    result = plan(field, start, goal, planner=planner, time_limit=1.0, robot_radius=0.1, max_risk=0.3,
                  risk_weight=2.0, seed=3)  # fmt: skip
    assert result.status == "exact"
    assert result.length == pytest.approx(5.0, abs=1e-9)
    assert result.cost == pytest.approx(7.5, abs=1e-9)
    assert result.mean_risk == pytest.approx(0.25)
    assert result.max_risk == pytest.approx(0.25)


@pytest.mark.parametrize("planner", ["grid", "RRTstar"])
def test_crossing_a_risky_band_costs_its_dilated_width(planner: str) -> None:
    # a band of risk 0.5, 1 m wide, across the whole map; the footprint (0.1 m = 2 cells, a
    # cell counts while the gap to it is below the radius) widens it by 2 cells on each side
    risk = np.zeros((200, 80), np.float32)
    risk[80:100, :] = 0.5
    field = RiskField(risk, RES, (0.0, 0.0))
    start, goal = (1.025, 2.025), (9.025, 2.025)
    result = plan(field, start, goal, planner=planner, time_limit=0.5, robot_radius=0.1, max_risk=0.6,
                  risk_weight=1.0, seed=4)  # fmt: skip
    assert result.status == "exact"
    assert result.length == pytest.approx(8.0, abs=1e-6)
    assert result.cost == pytest.approx(8.0 + 0.5 * (1.0 + 2 * 2 * RES), abs=1e-6)
    assert result.max_risk == pytest.approx(0.5)


def test_zero_weight_costs_the_length_only() -> None:
    risk = np.full((60, 60), 0.4, np.float32)
    field = RiskField(risk, RES, (0.0, 0.0))
    result = plan(field, (0.5, 0.5), (2.5, 2.0), planner="grid", robot_radius=0.0, risk_weight=0.0)
    assert result.cost == pytest.approx(result.length)


def test_reported_measures_agree_with_the_path() -> None:
    rng = np.random.default_rng(11)
    risk = (rng.random((80, 80)) * 0.5).astype(np.float32)
    field = RiskField(risk, RES, (0.0, 0.0))
    result = plan(field, (0.3, 0.3), (3.7, 3.6), planner="RRTstar", time_limit=0.3, robot_radius=0.05,
                  max_risk=0.6, risk_weight=3.0, seed=5)  # fmt: skip
    assert result.status == "exact"
    steps = np.linalg.norm(np.diff(result.path, axis=0), axis=1)
    assert result.length == pytest.approx(steps.sum())
    assert steps.max() <= RES + 1e-9  # interpolated at the map resolution
    assert result.cost == pytest.approx(result.length * (1.0 + 3.0 * result.mean_risk))
    assert result.max_risk <= 0.6
    assert np.allclose(result.path[0], (0.3, 0.3)) and np.linalg.norm(result.path[-1] - (3.7, 3.6)) <= RES


def test_optimizing_planners_come_close_to_the_grid_optimum() -> None:
    # a risky blob across the straight line: the best path trades length for risk
    x = (np.arange(120) + 0.5) * RES
    xx, yy = np.meshgrid(x, x, indexing="ij")
    risk = (0.55 * np.exp(-((xx - 3.0) ** 2 + (yy - 3.0) ** 2) / 2.0)).astype(np.float32)
    field = RiskField(risk, RES, (0.0, 0.0))
    kwargs = dict(robot_radius=0.1, max_risk=0.6, risk_weight=2.0)
    grid = plan(field, (0.5, 0.5), (5.5, 5.5), planner="grid", **kwargs)
    straight = 5.0 * np.sqrt(2.0)
    assert grid.length > straight + 0.1  # the detour is worth it
    for planner in ("RRTstar", "BITstar"):
        result = plan(field, (0.5, 0.5), (5.5, 5.5), planner=planner, time_limit=0.5, seed=6, **kwargs)
        assert result.status == "exact"
        assert result.cost <= 1.05 * grid.cost
