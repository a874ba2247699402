"""Compiled validity, motion checks and objective (planning/native.py): same answers, same plans, safe fallback."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

import planning.ompl_solve
from planning import RiskField, native, plan
from planning.packed import PackedGrid
from planning.spaces import STATE_SPACES

RES = 0.05
SPACES_3 = {"R2": 2, "SE2": 2, "Dubins": 2, "R3": 3}


def _field(ndim: int, seed: int = 3, walls: bool = False) -> RiskField:
    rng = np.random.default_rng(seed)
    shape = (90, 70) if ndim == 2 else (30, 25, 12)
    origin = (-1.3, 2.1) if ndim == 2 else (-1.3, 2.1, 0.4)
    risk = (rng.random(shape) * 0.5).astype(np.float32)
    if walls:  # one-cell walls and scattered blocked cells: validity answers of both kinds
        risk[::9] = 1.0
        risk[rng.random(shape) < 0.02] = 1.0
    return RiskField(risk, RES, origin)


def _build(space: str, field: RiskField, *, enabled: bool, weight: float = 2.5):
    grid = PackedGrid(field, 0.05, 0.6, True, weight, 0.4 if space == "Dubins" else None)
    native.set_enabled(enabled)
    try:
        return grid, STATE_SPACES[space].build(grid, 0.4 if space == "Dubins" else None)
    finally:
        native.set_enabled(True)


def _random_states(space, field: RiskField, rng: np.random.Generator, n: int):
    low = np.asarray(field.origin)
    high = low + np.asarray(field.shape) * field.resolution
    for _ in range(n):
        p = rng.uniform(low, high)
        yield space.to_state((*p, rng.uniform(-math.pi, math.pi)))  # R2 and R3 ignore the extra angle


@pytest.mark.parametrize("name", list(SPACES_3))
def test_native_costs_equal_the_python_objective_bit_for_bit(name: str) -> None:
    field = _field(SPACES_3[name])
    _, fast = _build(name, field, enabled=True)
    _, slow = _build(name, field, enabled=False)
    assert len(fast.native) == 3, native.status()  # validity, motion and objective compiled
    assert slow.native == ()
    rng = np.random.default_rng(9)
    states = list(_random_states(fast, field, rng, 400))
    for a, b in zip(states[::2], states[1::2], strict=True):
        assert fast.objective.motionCost(a, b).value() == slow.objective.motionCost(a, b).value()
    fast.close()


@pytest.mark.parametrize("name", list(SPACES_3))
def test_native_heuristic_is_the_length_and_never_above_the_cost(name: str) -> None:
    field = _field(SPACES_3[name])
    _, space = _build(name, field, enabled=True)
    assert space.native, native.status()
    rng = np.random.default_rng(5)
    states = list(_random_states(space, field, rng, 200))
    for a, b in zip(states[::2], states[1::2], strict=True):
        h = space.objective.motionCostHeuristic(a, b).value()
        assert h == pytest.approx(space.si.distance(a, b), rel=1e-12)
        assert h <= space.objective.motionCost(a, b).value() + 1e-12
    space.close()


def test_released_objective_costs_plain_length_and_its_table_is_reused() -> None:
    field = _field(2)
    _, space = _build("R2", field, enabled=True)
    a, b = space.to_state((0.0, 3.0)), space.to_state((2.0, 4.5))
    assert space.objective.motionCost(a, b).value() > math.hypot(2.0, 1.5)  # risk adds to the length
    space.close()
    space.close()  # idempotent
    assert space.objective.motionCost(a, b).value() == pytest.approx(math.hypot(2.0, 1.5))
    for _ in range(20):
        plan(field, (0.0, 3.0), (2.0, 4.5), planner="RRTstar", time_limit=0.05, robot_radius=0.0, seed=1)
    assert native._classes
    for cls in native._classes.values():
        assert len(cls.tables) <= 2  # released tables are reused, not one per plan
        assert len(cls.free) == len(cls.tables)


@pytest.mark.parametrize(("name", "start", "goal"), [
    ("R2", (0.0, 3.0), (2.7, 5.2)),
    ("Dubins", (0.0, 3.0, 0.0), (2.7, 5.2, 1.0)),
    ("R3", (-1.0, 2.4, 0.5), (0.0, 3.2, 0.9)),
])  # fmt: skip
def test_seeded_plans_are_identical_compiled_and_in_python(name, start, goal) -> None:
    field = _field(len(start) if name == "R3" else 2)
    # a generous time limit: the iteration count, not the clock, ends both runs (Python is slower)
    kw = dict(planner="RRTstar", state_space=name, time_limit=20.0, max_iterations=2000, robot_radius=0.05,
              max_risk=0.6, risk_weight=2.0, seed=11, turning_radius=0.4 if name == "Dubins" else None)  # fmt: skip
    fast = plan(field, start, goal, **kw)
    native.set_enabled(False)
    try:
        slow = plan(field, start, goal, **kw)
    finally:
        native.set_enabled(True)
    assert all(native.status()[f"{kind} {name}"] == "native" for kind in native.KINDS)
    assert fast.status == slow.status == "exact"
    assert planning.ompl_solve.CLOCK_NOTE not in fast.message + slow.message
    np.testing.assert_array_equal(fast.path, slow.path)
    assert fast.cost == slow.cost


def test_a_failed_check_falls_back_to_python_with_one_warning(monkeypatch, caplog) -> None:
    monkeypatch.setattr(native, "_verdicts", {})
    monkeypatch.setattr(native, "_state_layout_ok", lambda space, si: False)
    field = _field(2)
    with caplog.at_level(logging.WARNING, logger="planning.native"):
        # max_risk 0.6: the field's risks run up to 0.5 (the default would block parts of it)
        first = plan(field, (0.0, 3.0), (2.7, 5.2), planner="RRTstar", time_limit=0.2, robot_radius=0.05, seed=2,
                     max_risk=0.6)
        second = plan(field, (0.0, 3.0), (2.7, 5.2), planner="RRTstar", time_limit=0.2, robot_radius=0.05, seed=2,
                      max_risk=0.6)
    assert first.status == second.status == "exact"
    assert all("not laid out as expected" in native.status()[f"{kind} R2"] for kind in native.KINDS)
    warnings = [r for r in caplog.records if r.name == "planning.native"]
    assert len(warnings) == len(native.KINDS)  # one per kind, not one per plan
    assert all("using the Python one" in w.getMessage() for w in warnings)
    _, space = _build("R2", field, enabled=True)
    assert space.native == () and type(space.objective).__name__ == "RiskCostR2"


def test_reeds_shepp_keeps_the_python_objective() -> None:
    field = _field(2)
    grid = PackedGrid(field, 0.05, 0.6, True, 1.0, 0.4)
    space = STATE_SPACES["ReedsShepp"].build(grid, 0.4)
    assert space.native == ()
    assert type(space.objective).__name__ == "RiskCostCurve"


@pytest.mark.parametrize("name", list(SPACES_3))
def test_native_validity_and_motion_checks_answer_as_the_python_ones(name: str) -> None:
    field = _field(SPACES_3[name], walls=True)
    _, fast = _build(name, field, enabled=True)
    _, slow = _build(name, field, enabled=False)
    assert len(fast.native) == 3
    rng = np.random.default_rng(21)
    states = list(_random_states(fast, field, rng, 600))
    answers = [bool(fast.si.isValid(s)) for s in states]
    assert answers == [bool(slow.si.isValid(s)) for s in states]
    assert 0 < sum(answers) < len(answers)  # both answers occur
    # long segments, and short ones (up to 6 cells) from each state, along its heading in SE2
    ends = list(_random_states(fast, field, rng, 300))
    shorts = []
    for a in states[:300]:
        v = np.asarray(fast.values(a), dtype=float)
        if name in ("SE2", "Dubins"):
            d = rng.uniform(0.0, 6 * RES)
            shorts.append(fast.to_state((v[0] + d * math.cos(v[2]), v[1] + d * math.sin(v[2]), v[2])))
        else:
            shorts.append(fast.to_state(tuple(v + rng.uniform(-3 * RES, 3 * RES, len(v)))))
    pairs = list(zip(states[:300], ends, strict=True)) + list(zip(states[:300], shorts, strict=True))
    moves = [bool(fast.si.checkMotion(a, b)) for a, b in pairs]
    assert moves == [bool(slow.si.checkMotion(a, b)) for a, b in pairs]
    assert 0 < sum(moves) < len(moves)
    fast.close()


def test_a_seeded_plan_repeats_on_a_machine_that_runs_it_slower() -> None:
    # The Python objective runs RRTstar about half as fast as the compiled one, as a loaded
    # machine would; the default budget of a seeded plan (no max_iterations) must still end both.
    field = _field(2)
    kw = dict(planner="RRTstar", time_limit=0.3, robot_radius=0.05, seed=4, grid_seed=False, max_risk=0.6)
    fast = plan(field, (0.0, 3.0), (2.7, 5.2), **kw)
    native.set_enabled(False)
    try:
        slow = plan(field, (0.0, 3.0), (2.7, 5.2), **kw)
    finally:
        native.set_enabled(True)
    assert fast.stopped_by == slow.stopped_by == "iterations"
    assert fast.iterations == slow.iterations
    assert planning.ompl_solve.CLOCK_NOTE not in fast.message + slow.message
    np.testing.assert_array_equal(fast.path, slow.path)
    assert slow.planning_time <= planning.wall_clock_limit(0.3, seeded=True) + 0.2
