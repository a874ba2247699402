"""A prior (a saved map's cells) fused as agreeing scans: ``integrate_prior``, ``prior_risks``, ``prior_levels``."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from fuzzyocc import BayesMap, FuzzyEngine, FuzzyMap, GridSpec, LaserScan, SensorModel
from fuzzyocc.maps import MAX_PRIOR_SCANS, PRIOR_UNSEEN, OccupancyMap

SPEC = GridSpec(origin=(0.0, 0.0), size=(10.0, 1.0), resolution=0.1)  # 100 x 10 cells
SENSOR = SensorModel(range_sigma=0.03)  # floored at half a cell: sigma 0.05 m
WALL, CROSSED, ROW = 80, 29, 5  # the wall cell (centre x = 8.05), a cell 102 sigmas in front of it, the row

MAKERS: dict[str, Callable[[], OccupancyMap]] = {
    "evidence": lambda: FuzzyMap(SPEC, SENSOR),
    "paper": lambda: FuzzyMap(SPEC, SENSOR, FuzzyEngine.paper()),
    "bayes": lambda: BayesMap(SPEC, SENSOR),
}


def _beam(range_m: float) -> LaserScan:
    """One beam along row 5 from the centre of cell 0: a hit at ``range_m`` lands 0.05 + range_m along x."""
    return LaserScan(pose=(0.05, 0.55, 0.0), angle_min=0.0, angle_increment=0.01, ranges=[range_m], range_min=0.1,
                     range_max=20.0)


def _state(m: OccupancyMap, i: int) -> np.ndarray:
    arrays = m.to_arrays()
    return np.asarray(arrays["state"][i, ROW] if "state" in arrays else arrays["logodds"][i, ROW])


def _prior(m: OccupancyMap, cells: dict[int, int]) -> None:
    levels = np.full(SPEC.shape, PRIOR_UNSEEN, dtype=np.int8)
    for i, level in cells.items():
        levels[i, ROW] = level
    m.integrate_prior(levels)


@pytest.mark.parametrize("engine", list(MAKERS))
@pytest.mark.parametrize("k", [1, 2, 3])
def test_k_prior_scans_leave_a_cell_as_k_real_scans_do(engine: str, k: int) -> None:
    scanned, prior = MAKERS[engine](), MAKERS[engine]()
    for _ in range(k):
        scanned.integrate_batch([_beam(8.0)])  # ends at the wall cell's centre
    _prior(prior, {WALL: k, CROSSED: -k})
    for cell in (WALL, CROSSED):
        assert np.array_equal(_state(prior, cell), _state(scanned, cell)), (engine, cell)
        assert prior.risk()[cell, ROW] == scanned.risk()[cell, ROW]
    assert prior.observed()[WALL, ROW] and prior.observed()[CROSSED, ROW]
    assert prior.scans_fused == 0  # a prior is no scan


@pytest.mark.parametrize("engine", list(MAKERS))
def test_an_obstacle_of_the_prior_seen_through_clears_as_one_scans_made_it(engine: str) -> None:
    """A wall the prior holds (2 scans' worth) and one made by 2 real scans go in as many scans that see past it."""

    def scans_to_clear(m: OccupancyMap) -> int:
        for n in range(1, 40):
            m.integrate_batch([_beam(9.0)])  # the wall is gone: the beam crosses its cell
            if m.risk()[WALL, ROW] < 0.45:
                return n
        raise AssertionError("never cleared")

    scanned, prior = MAKERS[engine](), MAKERS[engine]()
    for _ in range(2):
        scanned.integrate_batch([_beam(8.0)])
    _prior(prior, {WALL: 2})
    assert prior.risk()[WALL, ROW] > 0.6
    cleared = scans_to_clear(prior)
    assert cleared == scans_to_clear(scanned)
    # evidence: O4 steps down a level a scan; paper: OCC to UNK, then MPE; bayes: 2 x 0.61 log-odds, -0.62 a scan
    assert cleared == {"evidence": 5, "paper": 2, "bayes": 3}[engine]


@pytest.mark.parametrize("engine", list(MAKERS))
def test_prior_risks_are_what_the_map_reads_at_each_level(engine: str) -> None:
    m = MAKERS[engine]()
    risks = m.prior_risks(3)
    assert risks.shape == (7,) and risks.dtype == np.float32
    assert risks[3] == 0.5  # level 0: observed, no evidence
    assert np.all(np.diff(risks[3:]) >= 0) and np.all(np.diff(risks[:4]) >= 0)  # hits raise, pass-throughs lower
    assert risks[4] > 0.5 > risks[2]
    _prior(m, {10: -3, 11: -1, 12: 0, 13: 2, 14: 3})
    assert m.risk()[10:15, ROW].tolist() == [risks[0], risks[2], risks[3], risks[5], risks[6]]


def test_unseen_cells_stay_never_observed_and_level_zero_is_observed_unknown() -> None:
    m = MAKERS["evidence"]()
    _prior(m, {12: 0})
    observed = m.observed()
    assert observed[12, ROW] and observed.sum() == 1
    assert np.all(m.risk() == 0.5)


def test_prior_levels_take_the_ends_as_the_full_weight_and_the_rest_as_the_nearest_risk() -> None:
    m = MAKERS["evidence"]()  # levels -2..2 read 0.3, 0.4, 0.5, 0.7, 0.9
    p = np.array([np.nan, 0.0, 1.0, 0.5, 0.68, 0.42, 0.31, 0.95, 0.05])
    assert m.prior_levels(p, 2).tolist() == [PRIOR_UNSEEN, -2, 2, 0, 1, -1, -2, 2, -2]
    # capped at the weight: risk 0.1 is 4 pass-throughs away, 1 allows one
    assert m.prior_levels(np.array([0.1, 0.95]), 1).tolist() == [-1, 1]
    # a tie goes to fewer scans: midway between level -1 and level 0 (risks are multiples of 2**-16: exact)
    risks = m.prior_risks(1).astype(np.float64)
    assert m.prior_levels(np.array([(risks[0] + risks[1]) / 2, (risks[1] + risks[2]) / 2]), 1).tolist() == [0, 0]


@pytest.mark.parametrize("bad", [-0.1, 1.5, np.inf])
def test_prior_levels_refuse_what_is_not_a_probability(bad: float) -> None:
    with pytest.raises(ValueError, match="occupancy"):
        MAKERS["evidence"]().prior_levels(np.array([0.5, bad]), 2)


@pytest.mark.parametrize("weight", [0, MAX_PRIOR_SCANS + 1, 2.0, True])
def test_the_weight_is_a_whole_number_of_scans_within_bounds(weight: object) -> None:
    with pytest.raises(ValueError, match="weight"):
        MAKERS["evidence"]().prior_risks(weight)  # type: ignore[arg-type]


@pytest.mark.parametrize("levels", [
    np.zeros((100, 9), dtype=np.int8),
    np.zeros((100, 10), dtype=np.int16),
    np.full((100, 10), MAX_PRIOR_SCANS + 1, dtype=np.int8),
    np.full((100, 10), -MAX_PRIOR_SCANS - 1, dtype=np.int8),
])
def test_bad_levels_are_refused_and_change_nothing(levels: np.ndarray) -> None:
    m = MAKERS["evidence"]()
    before = m.to_arrays()
    with pytest.raises(ValueError, match="levels"):
        m.integrate_prior(levels)
    after = m.to_arrays()
    assert all(np.array_equal(before[key], after[key]) for key in before)


@pytest.mark.parametrize("engine", list(MAKERS))
def test_a_prior_then_scans_restore_bit_for_bit_from_the_arrays(engine: str) -> None:
    m = MAKERS[engine]()
    rng = np.random.default_rng(3)
    levels = rng.integers(-3, 4, size=SPEC.shape).astype(np.int8)
    levels[rng.random(SPEC.shape) < 0.3] = PRIOR_UNSEEN
    m.integrate_prior(levels)
    m.integrate_batch([_beam(8.0)])
    arrays = m.to_arrays()
    restored = (FuzzyMap.from_arrays(SPEC, SENSOR, arrays, m.engine) if isinstance(m, FuzzyMap)
                else BayesMap.from_arrays(SPEC, SENSOR, arrays))
    assert np.array_equal(restored.risk(), m.risk()) and np.array_equal(restored.observed(), m.observed())
    beam_only = MAKERS[engine]()
    beam_only.integrate_batch([_beam(8.0)])
    assert np.array_equal(m.observed(), (levels != PRIOR_UNSEEN) | beam_only.observed())
