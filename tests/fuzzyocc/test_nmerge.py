"""The n-input merge: one input is the 2-D fusion, n inputs do not depend on their order."""

import numpy as np
import pytest

from fuzzyocc import FuzzyEngine
from fuzzyocc.evidence import EVIDENCE_LABELS, evidence_engine
from fuzzyocc.nmerge import merge_n

ENGINES = {"paper": FuzzyEngine.paper(), "evidence": evidence_engine()}


def _states(engine: FuzzyEngine, n: int, rng: np.random.Generator) -> np.ndarray:
    """Fused states a map really holds: the unknown state fused with random measurements."""
    state = np.tile(engine.unknown_state(), (n, 1))
    for _ in range(3):
        state = engine.fuse(state, engine.fuzzify(rng.uniform(-8.0, 3.0, n)))
    return state


@pytest.mark.parametrize("name", list(ENGINES))
def test_one_input_is_the_two_input_fusion(name: str) -> None:
    engine, rng = ENGINES[name], np.random.default_rng(1)
    state = _states(engine, 500, rng)
    evidence = engine.fuzzify(rng.uniform(-8.0, 3.0, 500))
    merged = merge_n(engine, state, evidence, np.arange(501))
    assert np.array_equal(merged, engine.fuse(state, evidence))


@pytest.mark.parametrize("name", list(ENGINES))
def test_the_order_of_the_inputs_does_not_matter(name: str) -> None:
    engine, rng = ENGINES[name], np.random.default_rng(2)
    state = _states(engine, 200, rng)
    distances = rng.uniform(-8.0, 3.0, 200 * 4)
    groups = np.arange(0, 801, 4)
    merged = merge_n(engine, state, engine.fuzzify(distances), groups)
    shuffled = distances.reshape(200, 4)[:, rng.permutation(4)].reshape(-1)
    assert np.array_equal(merged, merge_n(engine, state, engine.fuzzify(shuffled), groups))


def test_the_evidence_engine_adds_the_steps_of_all_inputs() -> None:
    engine = evidence_engine()
    unknown = engine.unknown_state()[None, :]
    hit, free = engine.fuzzify(np.array([0.0]))[0], engine.fuzzify(np.array([-20.0]))[0]
    # one hit (+2) and one free reading (-1) at once: one level above unknown, as in sequence
    merged = merge_n(engine, unknown, np.stack([free, hit]), np.array([0, 2]))
    assert EVIDENCE_LABELS[int(np.argmax(merged[0]))] == "O1"
    sequential = engine.fuse(engine.fuse(unknown, hit[None, :]), free[None, :])
    assert np.array_equal(merged, sequential)


def test_a_cell_without_inputs_keeps_its_state_and_bad_groups_are_refused() -> None:
    engine = evidence_engine()
    state = np.tile(engine.unknown_state(), (2, 1))
    hit = engine.fuzzify(np.array([0.0]))
    merged = merge_n(engine, state, hit, np.array([0, 0, 1]))
    assert np.array_equal(merged[0], state[0]) and not np.array_equal(merged[1], state[1])
    with pytest.raises(ValueError, match="groups"):
        merge_n(engine, state, hit, np.array([0, 1, 0]))
    with pytest.raises(ValueError, match="min/max"):
        merge_n(FuzzyEngine.paper(and_op="product"), state[:, :7], hit[:, :7], np.array([0, 0, 1]))
