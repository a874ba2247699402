import math

import numpy as np
import pytest

from fuzzyocc.bayes import (
    BAYES_OCCUPIED_EXTENT,
    CLAMP_MAX,
    CLAMP_MIN,
    ELFES_MAX_CELLS,
    elfes_1d,
    logodds,
    merge,
    opdf,
    probability,
    update_logodds,
)


# ---------------------------------------------------------------- closed-form OPDF (eq. 4)
def test_opdf_levels_in_front_on_and_behind_the_surface() -> None:
    sigma = 0.03
    assert opdf(-20 * sigma, sigma) == pytest.approx(0.35, abs=1e-9)
    assert opdf(20 * sigma, sigma) == pytest.approx(0.5, abs=1e-9)
    assert opdf(0.0, sigma) == pytest.approx(0.35 + 0.15 / (1 + math.exp(-4)) + 0.15)


def test_opdf_peaks_near_the_surface_and_scales_with_sigma() -> None:
    d = np.linspace(-10.0, 10.0, 20001)
    p = opdf(d, 2.0)
    assert abs(d[np.argmax(p)]) < 0.5 * 2.0
    np.testing.assert_allclose(opdf(d * 3.0, 6.0), p)


def test_opdf_is_finite_without_warnings_far_from_the_surface() -> None:
    with np.errstate(over="raise", invalid="raise", divide="raise"):
        np.testing.assert_allclose(opdf(np.array([-1e6, 1e6]), 1e-3), [0.35, 0.5])


def test_opdf_refuses_non_positive_sigma() -> None:
    with pytest.raises(ValueError, match="sigma"):
        opdf(0.0, 0.0)


def test_bayes_occupied_extent_is_where_the_opdf_settles_at_one_half() -> None:
    t = np.linspace(BAYES_OCCUPIED_EXTENT, 50.0, 100_000)
    assert np.abs(opdf(t, 1.0) - 0.5).max() <= 1e-3
    just_before = np.linspace(BAYES_OCCUPIED_EXTENT - 0.02, BAYES_OCCUPIED_EXTENT, 100)
    assert np.abs(opdf(just_before, 1.0) - 0.5).max() > 1e-3


# ---------------------------------------------------------------- log-odds, merge (eq. 3), clamping
def test_logodds_and_probability_are_inverse() -> None:
    p = np.linspace(0.01, 0.99, 99)
    np.testing.assert_allclose(probability(logodds(p)), p)
    assert logodds(0.5) == 0.0
    assert probability(np.array([-1000.0, 1000.0])).tolist() == [0.0, 1.0]


def test_logodds_refuses_non_probabilities() -> None:
    with pytest.raises(ValueError, match="p must be probabilities"):
        logodds(1.5)


def test_clamps_are_octomaps_defaults() -> None:
    assert probability(CLAMP_MIN) == pytest.approx(0.1192)
    assert probability(CLAMP_MAX) == pytest.approx(0.971)


def test_merge_with_one_half_is_neutral_and_merge_is_commutative() -> None:
    p = np.linspace(0.05, 0.95, 19)
    np.testing.assert_allclose(merge(p, 0.5), p)
    np.testing.assert_allclose(merge(p, p[::-1]), merge(p[::-1], p))


def test_merge_is_a_sum_in_logodds() -> None:
    a, b = 0.7, 0.2
    assert merge(a, b) == pytest.approx(probability(logodds(a) + logodds(b)))


def test_consistent_measurements_refine_and_contradictory_ones_cancel() -> None:
    assert merge(0.65, 0.65) > 0.65
    assert merge(0.35, 0.35) < 0.35
    assert merge(0.65, 0.35) == pytest.approx(0.5)


def test_merge_refuses_certain_contradiction_and_bad_probabilities() -> None:
    with pytest.raises(ValueError, match="certain 0 with a certain 1"):
        merge(0.0, 1.0)
    with pytest.raises(ValueError, match="p2 must be probabilities"):
        merge(0.5, -0.1)


def test_update_logodds_saturates_at_the_clamps() -> None:
    hit, miss = float(logodds(0.7)), float(logodds(0.4))
    cell = np.zeros(1, dtype=np.float32)
    for _ in range(100):
        cell = update_logodds(cell, hit)
    assert cell.dtype == np.float32
    assert cell[0] == pytest.approx(CLAMP_MAX)
    for _ in range(100):
        cell = update_logodds(cell, miss)
    assert cell[0] == pytest.approx(CLAMP_MIN)


def test_a_saturated_cell_changes_its_mind_in_a_bounded_number_of_updates() -> None:
    empty = float(logodds(opdf(-10.0, 1.0)))  # far in front of a surface
    needed = math.ceil(CLAMP_MAX / -empty)
    cell = np.array([CLAMP_MAX])
    for _ in range(needed):
        cell = update_logodds(cell, empty)
    assert probability(cell)[0] < 0.5


# ---------------------------------------------------------------- Elfes' exact 1-D Bayes (eqs. 1-2)
def first_hit_posterior(n: int, cell: float, r: float, sigma: float, prior: float) -> np.ndarray:
    """The same posterior derived by hand: condition on which cell is hit first.

    P(first = k) = (1 - prior)^k prior (k = n: no cell occupied, the virtual wall);
    given first = k, cell i is empty for i < k, occupied for i = k and at its prior after.
    """
    centres = (np.arange(n + 1) + 0.5) * cell
    p_first = (1 - prior) ** np.arange(n + 1) * np.append(np.full(n, prior), 1.0)
    weight = p_first * np.exp(-0.5 * ((r - centres) / sigma) ** 2)
    i, k = np.arange(n)[:, None], np.arange(n + 1)[None, :]
    occupied_given_first = np.where(i < k, 0.0, np.where(i == k, 1.0, prior))
    return occupied_given_first @ weight / weight.sum()


def test_elfes_equals_the_first_hit_derivation() -> None:
    for prior in (0.5, 0.2):
        exact = elfes_1d(10, 5.0, 31.0, 4.0, prior=prior)
        np.testing.assert_allclose(exact, first_hit_posterior(10, 5.0, 31.0, 4.0, prior), rtol=1e-9)


def test_closed_form_follows_the_exact_shape() -> None:
    # The paper's figure 2 set-up in small: 5 mm cells, surface in cell 8 (centre 42.5 mm).
    cell, sigma, n, surface = 5.0, 5.0, 14, 42.5
    exact = elfes_1d(n, cell, surface, sigma)
    centres = (np.arange(n) + 0.5) * cell
    closed = opdf(centres - surface, sigma)
    front, behind = centres < surface - 3 * sigma, centres > surface + 2.5 * sigma
    assert np.argmax(exact) == np.argmax(closed) == 8
    assert (exact[front] < 0.05).all() and (closed[front] < 0.5).all()
    np.testing.assert_allclose(exact[behind], 0.5, atol=0.01)
    np.testing.assert_allclose(closed[behind], 0.5, atol=0.01)
    assert exact[8] > 0.5 and closed[8] > 0.5


def test_elfes_reading_at_the_far_wall_empties_the_line() -> None:
    p = elfes_1d(8, 1.0, 8.5, 0.3, prior=0.5)  # the virtual wall beyond the grid
    assert (p < 0.5).all()


def test_elfes_refuses_too_many_cells_naming_n_cells() -> None:
    with pytest.raises(ValueError, match=f"n_cells={ELFES_MAX_CELLS + 1} is above the limit"):
        elfes_1d(ELFES_MAX_CELLS + 1, 1.0, 5.0, 1.0)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"n_cells": 0}, "n_cells"),
        ({"cell_size": -1.0}, "cell_size"),
        ({"sigma": 0.0}, "sigma"),
        ({"measured_range": math.inf}, "measured_range"),
        ({"prior": 1.0}, "prior"),
    ],
)
def test_elfes_refuses_bad_arguments(kwargs: dict, field: str) -> None:
    args = {"n_cells": 4, "cell_size": 1.0, "measured_range": 2.0, "sigma": 0.5, **kwargs}
    with pytest.raises(ValueError, match=field):
        elfes_1d(**args)
