"""Growing maps: no box, cells on the lattice anchored at the frame's origin, memory for what rays reached."""

import numpy as np
import pytest

from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LatticeSpec, PointCloud, SensorModel
from fuzzyocc.carmen import read_carmen
from tests.conftest import carmen_log

SENSOR = SensorModel(range_sigma=0.03)


@pytest.fixture(scope="module")
def orebro() -> list:
    return read_carmen(carmen_log("orebro-corrected.log.gz"))[:120]


def _clouds(rng: np.random.Generator, n: int, centre: np.ndarray, spread: float = 3.0) -> list[PointCloud]:
    out = []
    for _ in range(n):
        origin = centre + rng.uniform(-spread, spread, 3)
        points = origin + rng.normal(size=(400, 3)) * np.array([4.0, 4.0, 1.0])
        out.append(PointCloud(points=points, origin=tuple(origin), range_max=6.0))
    return out


def test_a_growing_map_equals_the_fixed_map_of_its_bounds_cell_for_cell(orebro: list) -> None:
    grown = FuzzyMap(LatticeSpec(2, 0.05), SENSOR)
    for scan in orebro:
        grown.integrate_batch([scan])
    bounds = grown.bounds()
    assert bounds is not None and min(bounds.lo) < 0  # the log reaches below the frame's origin
    fixed = FuzzyMap(bounds.spec(), SENSOR)  # the box aligned to the same cells
    for scan in orebro:
        fixed.integrate_batch([scan])
    assert grown.risk().shape == bounds.shape == fixed.spec.shape
    np.testing.assert_array_equal(grown.risk(), fixed.risk())
    np.testing.assert_array_equal(grown.observed(), fixed.observed())
    assert grown.observed()[0].any() and grown.observed()[:, 0].any()  # the bounds are tight


def test_a_growing_3d_map_equals_the_fixed_map_of_its_bounds() -> None:
    clouds = _clouds(np.random.default_rng(1), 8, np.array([-2.0, 1.0, 0.5]))
    grown = FuzzyMap(LatticeSpec(3, 0.1), SENSOR)
    grown.integrate_batch(clouds)
    fixed = FuzzyMap(grown.bounds().spec(), SENSOR)
    fixed.integrate_batch(clouds)
    np.testing.assert_array_equal(grown.risk(), fixed.risk())
    np.testing.assert_array_equal(grown.observed(), fixed.observed())


def test_space_no_ray_reached_costs_nothing_wherever_the_robot_goes() -> None:
    m = FuzzyMap(LatticeSpec(3, 0.1), SENSOR)
    assert m.bounds() is None and m.held_cells() == 0 and m.state_nbytes() == 0
    assert m.risk().shape == (0, 0, 0)
    rng = np.random.default_rng(2)
    m.integrate_batch(_clouds(rng, 2, np.zeros(3)))
    near = m.held_cells()
    m.integrate_batch(_clouds(rng, 2, np.array([9e5, -9e5, 10.0])))  # 1,270 km away
    assert m.held_cells() < 2.5 * near  # the space between costs nothing
    bounds = m.bounds()
    assert bounds.origin[0] < 0 < 9e5 - 10 < bounds.upper[0]
    # anywhere is answered: never observed is unknown
    np.testing.assert_array_equal(m.risk_at(np.array([[5e5, 0.0, 0.0], [-3e5, 2e5, -40.0]])), [0.5, 0.5])
    with pytest.raises(ValueError, match="points\\[0\\]"):
        m.risk_at(np.array([[2e7, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="points\\[1\\]"):
        m.risk_at(np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]))


def test_risk_at_agrees_with_the_risk_of_the_bounds(orebro: list) -> None:
    m = FuzzyMap(LatticeSpec(2, 0.05), SENSOR)
    m.integrate_batch(orebro[:30])
    w = m.bounds()
    ij = np.stack(np.meshgrid(np.arange(w.shape[0]), np.arange(w.shape[1]), indexing="ij"), -1).reshape(-1, 2)
    centres = np.asarray(w.origin) + (ij + 0.5) * 0.05
    np.testing.assert_array_equal(m.risk_at(centres), m.risk().reshape(-1))


def test_a_window_cuts_the_read_and_is_empty_outside(orebro: list) -> None:
    m = FuzzyMap(LatticeSpec(2, 0.05), SENSOR)
    m.integrate_batch(orebro[:30])
    whole = m.window()
    part = m.window((0.0, 0.0), (2.0, 1.0))
    assert part.origin == pytest.approx((0.0, 0.0)) and part.shape == (41, 21)  # cells meeting [0, 2] x [0, 1]
    lo = [p - w for p, w in zip(part.lo, whole.lo)]
    np.testing.assert_array_equal(m.risk(part), m.risk()[lo[0]:lo[0] + 41, lo[1]:lo[1] + 21])
    assert m.window((1e4, 1e4), None) is None
    with pytest.raises(ValueError, match="low"):
        m.window((0.0, np.inf), None)


def test_restored_growing_map_is_the_same_map_and_fuses_the_same(orebro: list) -> None:
    m = FuzzyMap(LatticeSpec(2, 0.05), SENSOR)
    m.integrate_batch(orebro[:60])
    restored = FuzzyMap.from_arrays(LatticeSpec(2, 0.05), SENSOR, m.to_arrays())
    assert restored.state_nbytes() == m.state_nbytes() and restored.scans_fused == 60
    np.testing.assert_array_equal(restored.risk(), m.risk())
    m.integrate_batch(orebro[60:])
    restored.integrate_batch(orebro[60:])
    np.testing.assert_array_equal(restored.risk(), m.risk())
    np.testing.assert_array_equal(restored.observed(), m.observed())
    arrays = m.to_arrays()
    arrays["block_coords"] = arrays["block_coords"][:-1]
    with pytest.raises(ValueError, match="block"):
        FuzzyMap.from_arrays(LatticeSpec(2, 0.05), SENSOR, arrays)
    arrays = m.to_arrays()
    arrays["block_coords"][-1] = arrays["block_coords"][0]  # a block held twice: its cells would be two
    with pytest.raises(ValueError, match="a block twice"):
        FuzzyMap.from_arrays(LatticeSpec(2, 0.05), SENSOR, arrays)


@pytest.mark.parametrize("growing", [True, False], ids=["growing", "fixed"])
def test_clearing_a_box_makes_its_cells_never_observed_and_frees_their_blocks(orebro: list, growing: bool) -> None:
    spec = LatticeSpec(2, 0.05) if growing else GridSpec(origin=(-40.0, -50.0), size=(90.0, 100.0), resolution=0.05)
    m = FuzzyMap(spec, SENSOR)
    m.integrate_batch(orebro[:60])
    held = m.held_cells()
    box = m.window((-3.0, -3.0), (4.0, 5.0))
    observed_before = int(m.observed(box).sum())
    assert observed_before > 1000
    assert m.clear((-3.0, -3.0), (4.0, 5.0)) == observed_before
    assert not m.observed(box).any()
    assert np.all(m.risk(box) == 0.5)
    assert m.held_cells() < held  # the blocks wholly inside went back to costing nothing
    assert m.clear((-3.0, -3.0), (4.0, 5.0)) == 0
    with pytest.raises(ValueError, match="high"):
        m.clear((1.0, 1.0), (0.0, 2.0))


def test_forgetting_keeps_the_map_near_the_robot_and_does_not_depend_on_batching(orebro: list) -> None:
    one, five = FuzzyMap(LatticeSpec(2, 0.05), SENSOR), FuzzyMap(LatticeSpec(2, 0.05), SENSOR)
    one.forget_beyond = five.forget_beyond = 6.0
    for scan in orebro:
        one.integrate_batch([scan])
    for i in range(0, len(orebro), 5):
        five.integrate_batch(orebro[i:i + 5])
    np.testing.assert_array_equal(one.risk(), five.risk())
    np.testing.assert_array_equal(one.observed(), five.observed())
    w = one.bounds()
    ij = np.argwhere(one.observed())
    centres = np.asarray(w.origin) + (ij + 0.5) * 0.05
    last = np.asarray(orebro[-1].pose[:2])
    assert np.linalg.norm(centres - last, axis=1).max() <= 6.0
    kept = FuzzyMap(LatticeSpec(2, 0.05), SENSOR)
    kept.integrate_batch(orebro)
    assert one.held_cells() < kept.held_cells() / 2
    with pytest.raises(ValueError, match="forget_beyond"):
        one.forget_beyond = -1.0


def test_growing_maps_are_fuzzy_and_refuse_a_too_fine_lattice() -> None:
    with pytest.raises(ValueError, match="fixed box"):
        BayesMap(LatticeSpec(2, 0.05))
    with pytest.raises(ValueError, match="at least"):
        LatticeSpec(2, 0.001)
    with pytest.raises(ValueError, match="ndim"):
        LatticeSpec(4, 0.1)
