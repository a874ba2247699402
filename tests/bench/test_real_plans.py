"""Planning on a real map, CI-sized: what ``bench planning``'s real-map section measures with.

One small real map, orebro's first 120 scans fused with the default engine (as
``tests/bench/test_map_quality.py`` takes them), 3 queries between far-apart poses the robot drove
(``bench/_plan_audit.pick_pairs``). The grid planner and RRTstar (seeded, on a fixed iteration count
with a time limit it never reaches, so the plans repeat on any machine; as ``plan`` runs it by default)
must reach the goal, and with RRTstar on its own (without the grid planner's path as a seed) keep the
robot radius less one cell from our map's occupied cells (risk >= 0.6); on its own it may stop short
(since the default ``max_risk`` 0.45, one of the three queries passes a door it misses in 25,000
iterations). The same cost grid searched by
scikit-image (Dijkstra) must cost what our A* found, and pyastar2d must find every query too. No
times are asserted: they are the benchmark's to print.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench import _logmaps, _plan_audit, _real_plans
from tests.conftest import carmen_log

SCANS = 120  # bench_maps.QUICK_SCANS: the CI-sized part of the smallest recorded log
PAIRS = 3
CLEAR = _real_plans.ROBOT_RADIUS - _logmaps.RESOLUTION - 1e-9  # the radius less one cell


@pytest.fixture(scope="module")
def small_map() -> _real_plans.RealMap:
    orebro = carmen_log("orebro-corrected.log.gz")  # from tests/data; fails, not skips, without it
    return _real_plans.build_map(orebro, pairs=PAIRS, scans=SCANS)


@pytest.fixture(scope="module")
def plans(small_map: _real_plans.RealMap) -> list[_real_plans.PlanRun]:
    # RRTstar as plan() runs it by default, and alone (grid_seed=False) where plan() seeds it with the grid's path
    return _real_plans.run_planners(small_map, ["RRTstar"], time_limit=_plan_audit.FIXED_TIME_LIMIT,
                                    max_iterations=_plan_audit.FIXED_ITERATIONS, alone=True)


def test_the_queries_are_far_apart_poses_valid_on_the_map(small_map: _real_plans.RealMap) -> None:
    rm = small_map
    assert rm.scans == SCANS and rm.cells > 100_000
    assert len(rm.queries) == PAIRS
    valid = rm.field.valid_mask(_real_plans.ROBOT_RADIUS, _real_plans.MAX_RISK)
    for q in rm.queries:
        assert q.apart >= _plan_audit.MIN_APART * math.hypot(*rm.spec.size)
        assert valid[_real_plans.cell(rm.spec, q.start)] and valid[_real_plans.cell(rm.spec, q.goal)]


def test_grid_and_rrtstar_are_exact_and_clear_of_occupied_cells(plans: list[_real_plans.PlanRun]) -> None:
    labels = {"grid", "RRTstar", *(["RRTstar (alone)"] if _real_plans.can_plan_alone() else [])}
    assert {r.label for r in plans} == labels and len(plans) == len(labels) * PAIRS
    for r in plans:
        # what a user gets (the grid planner, RRTstar as plan() runs it) reaches the goal; the sampler on its own
        # need not (it misses doors the cell graph finds, why plan() seeds it), but it keeps clear
        assert r.exact or (r.alone and r.status == "approximate"), (r.planner, r.pair, r.status, r.message)
        assert r.clearance >= CLEAR, (r.planner, r.pair, r.clearance)
        assert math.isfinite(r.cost) and r.cost >= r.length > 0
    for label in labels - {"grid"}:
        ratios = _real_plans.cost_ratios(plans, label)
        assert all(math.isfinite(x) and x > 0 for x in ratios)
        assert len(ratios) == PAIRS if label == "RRTstar" else len(ratios) >= 1


def test_a_seeded_plan_on_a_fixed_budget_repeats(small_map: _real_plans.RealMap,
                                                 plans: list[_real_plans.PlanRun]) -> None:
    q = small_map.queries[0]
    alone = _real_plans.can_plan_alone()
    again = _real_plans.plan_once(small_map, q, "RRTstar", _plan_audit.FIXED_TIME_LIMIT, _plan_audit.FIXED_ITERATIONS,
                                  alone=alone)
    first = next(r for r in plans if r.planner == "RRTstar" and r.alone == alone and r.pair == q.pair)
    assert (again.status, again.cost, again.clearance) == (first.status, first.cost, first.clearance)


def test_the_cost_grid_is_the_planners_validity_and_cost(small_map: _real_plans.RealMap) -> None:
    weights = _real_plans.cost_grid(small_map)
    valid = small_map.field.valid_mask(_real_plans.ROBOT_RADIUS, _real_plans.MAX_RISK)
    dilated = small_map.field.dilated_risk(_real_plans.ROBOT_RADIUS)
    assert weights.dtype == np.float32 and weights.shape == small_map.spec.shape
    assert np.array_equal(np.isinf(weights), ~valid)
    assert np.allclose(weights[valid], 1.0 + _real_plans.RISK_WEIGHT * dilated[valid], rtol=1e-7)


def test_scikit_image_finds_our_optimum_and_pyastar2d_every_path(small_map: _real_plans.RealMap) -> None:
    timings = _real_plans.grid_baselines(small_map, repeats=1)
    assert len(timings) == PAIRS
    for t in timings:
        assert t.ours_found and t.pyastar_found and t.skimage_found, t
        # the same edge cost by Dijkstra: our A* is optimal on the cell graph (float32 weights vs float64)
        assert t.ours_graph_cost == pytest.approx(t.skimage_cost, rel=1e-6), t
        assert min(t.ours_search, t.ours_plan, t.pyastar, t.pyastar_core, t.skimage) > 0
