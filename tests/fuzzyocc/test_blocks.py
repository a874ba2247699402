"""FuzzyMap's uniform-block storage against a dense reference: same states, risk, observed, bit for bit."""

import numpy as np
import pytest

from fuzzyocc import FuzzyEngine, FuzzyMap, GridSpec, PointCloud, SensorModel
from fuzzyocc.blockgrid import BlockGrid
from fuzzyocc.grid import CellGrid
from fuzzyocc.keys import flat_to_keys
from fuzzyocc.raycast import cast_rays

SENSOR = SensorModel(range_sigma=0.03)
# Odd sizes: edge blocks are cut by the grid on every axis (33 x 29 x 13 and 37 x 21 cells).
SPEC_3D = GridSpec(origin=(-0.2, 0.1, 0.0), size=(3.3, 2.9, 1.3), resolution=0.1)
SPEC_2D = GridSpec(origin=(0.0, -0.3), size=(3.7, 2.1), resolution=0.1)
SPEC_THIN = GridSpec(origin=(0.0, 0.0, 0.0), size=(2.5, 1.9, 0.2), resolution=0.1)  # 2 cells thick


def fuse_at(engine: FuzzyEngine, state: np.ndarray, cells: np.ndarray, evidence: np.ndarray) -> None:
    """``state[cells] = engine.fuse(state[cells], evidence)``: a dense map's fusion, in place.

    ``cells`` are unique, as one scan's are: a cell listed twice would be fused once.
    """
    assert np.unique(cells).size == cells.size
    state[cells] = engine.fuse(state[cells], evidence)


class DenseReference:
    """The dense map the block storage replaces: (num_cells, L) states fused in place by ``fuse_at``."""

    def __init__(self, spec: GridSpec, engine: FuzzyEngine) -> None:
        self.spec, self.engine = spec, engine
        self.state = np.tile(engine.unknown_state(), (spec.num_cells, 1)).astype(np.uint8)
        self.observed = np.zeros(spec.num_cells, dtype=bool)

    def integrate(self, cloud: PointCloud) -> None:
        rays = cloud.to_rays()
        sigma = np.maximum(SENSOR.sigma(rays.ranges, cloud.registration_sigma), 0.5 * self.spec.resolution)
        extent = self.engine.occupied_extent
        n = rays.ranges.size
        cast = cast_rays(self.spec, np.repeat(rays.origin[None], n, axis=0), rays.directions,
                         t_end=np.where(rays.hit, rays.ranges + extent * sigma, rays.ranges),
                         measured=np.where(rays.hit, rays.ranges, np.nan), sigma=sigma,
                         ray_offsets=np.array([0, n]), unknown_from=extent)
        self.observed[cast.cells] = True
        keep = np.isfinite(cast.distance_sigmas)
        fuse_at(self.engine, self.state, cast.cells[keep], self.engine.fuzzify(cast.distance_sigmas[keep]))

    def risk(self) -> np.ndarray:
        codes = np.rint(self.engine.defuzzify(self.state).astype(np.float64) * 2.0**16)
        return (codes.astype(np.float32) * np.float32(2.0**-16)).reshape(self.spec.shape)


def _clouds(spec: GridSpec, rng: np.random.Generator, n_scans: int) -> list[PointCloud]:
    """Sweeps from random poses inside the map to random points in and past it (hits and misses)."""
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    out = []
    for _ in range(n_scans):
        margin = np.minimum(0.2, 0.25 * (hi - lo))
        origin = rng.uniform(lo + margin, hi - margin)
        points = rng.uniform(lo - 0.3, hi + 0.3, size=(300, spec.ndim))
        out.append(PointCloud(points=points, origin=tuple(origin), range_max=float(rng.uniform(0.8, 3.0))))
    return out


def _clearing(spec: GridSpec, range_max: float = 10.0) -> PointCloud:
    """No-returns from the middle of the map through every cell centre: the map seen free up to ``range_max``."""
    keys = flat_to_keys(spec, np.arange(spec.num_cells))
    centres = np.asarray(spec.origin) + (keys + 0.5) * spec.resolution
    middle = 0.5 * (np.asarray(spec.origin) + np.asarray(spec.upper)) + 0.013  # off the cell faces
    away = centres - middle
    far = middle + 20.0 * away / np.linalg.norm(away, axis=1, keepdims=True)
    return PointCloud(points=far, origin=tuple(middle), range_max=range_max)


def _history(spec: GridSpec, seed: int) -> list[PointCloud]:
    """A ball around the middle seen free (every cell of the blocks inside it, unknown until then, takes
    the same evidence: they stay uniform), mixed scans, the map cleared several times (blocks
    collapse), then mixed again."""
    clouds = _clouds(spec, np.random.default_rng(seed), 6)
    return [_clearing(spec, range_max=1.0)] + clouds[:3] + [_clearing(spec)] * 4 + clouds[3:] + [_clearing(spec)] * 3


@pytest.mark.parametrize("spec", [SPEC_3D, SPEC_2D, SPEC_THIN], ids=["3d", "2d", "thin-3d"])
@pytest.mark.parametrize("engine", [FuzzyEngine.paper(), FuzzyEngine.paper(and_op="product", or_op="probsum")],
                         ids=["minmax", "product-probsum"])
def test_block_map_matches_the_dense_reference_scan_after_scan(spec: GridSpec, engine: FuzzyEngine) -> None:
    m, ref = FuzzyMap(spec, SENSOR, engine), DenseReference(spec, engine)
    sizes = [m.state_nbytes()]
    for cloud in _history(spec, 3):
        m.integrate_batch([cloud])
        sizes.append(m.state_nbytes())
        ref.integrate(cloud)
        arrays = m.to_arrays()
        np.testing.assert_array_equal(arrays["state"], ref.state.reshape(*spec.shape, -1))
        np.testing.assert_array_equal(arrays["observed"], ref.observed.reshape(spec.shape))
        np.testing.assert_array_equal(m.risk(), ref.risk())
    # The map grew (blocks expanded) and shrank (blocks collapsed) on the way: both were compared.
    steps = np.diff(sizes)
    assert np.any(steps > 0) and np.any(steps < 0)


def test_restored_block_map_is_the_same_map_and_fuses_the_same() -> None:
    clouds = _history(SPEC_3D, 5)
    m = FuzzyMap(SPEC_3D, SENSOR)
    m.integrate_batch(clouds[:6])
    risk_before = m.risk_at(np.array([[0.3, 0.5, 0.35]]))  # a partly refreshed cache must not leak
    restored = FuzzyMap.from_arrays(SPEC_3D, SENSOR, m.to_arrays())
    assert restored.state_nbytes() == m.state_nbytes()
    np.testing.assert_array_equal(restored.risk(), m.risk())
    assert restored.risk_at(np.array([[0.3, 0.5, 0.35]])) == risk_before
    for cloud in clouds[6:]:
        m.integrate_batch([cloud])
        restored.integrate_batch([cloud])
    a, b = m.to_arrays(), restored.to_arrays()
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    np.testing.assert_array_equal(m.risk(), restored.risk())


def test_risk_at_agrees_with_risk_in_every_cell() -> None:
    m = FuzzyMap(SPEC_3D, SENSOR)
    m.integrate_batch(_history(SPEC_3D, 9)[:5])
    keys = flat_to_keys(SPEC_3D, np.arange(SPEC_3D.num_cells))
    centres = np.asarray(SPEC_3D.origin) + (keys + 0.5) * SPEC_3D.resolution
    np.testing.assert_array_equal(m.risk_at(centres), m.risk().reshape(-1))


def test_uniform_space_costs_little_and_clearing_it_gives_the_memory_back() -> None:
    spec = GridSpec(origin=(0.0, 0.0, 0.0), size=(3.2, 3.2, 1.6), resolution=0.1)  # 16384 cells
    m = FuzzyMap(spec, SENSOR)
    fresh = m.state_nbytes()
    assert fresh == 0 and m.held_cells() == 0  # no ray yet: no block held
    # A dense fan of no-returns from the centre: free space everywhere it reaches, a ragged edge.
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(20000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    centre = np.array([1.6, 1.6, 0.8])
    cloud = PointCloud(points=centre + 5.0 * dirs, origin=tuple(centre), range_max=1.0)
    m.integrate_batch([cloud])
    once = m.state_nbytes()
    assert once > fresh
    for _ in range(6):  # the same sweep again: free stays free, the map does not grow
        m.integrate_batch([cloud])
    assert m.state_nbytes() <= once
    assert m.resident_nbytes() >= m.state_nbytes()
    # Clearing the whole box until every cell is saturated free makes every block uniform
    # again: one row a block (4 x 4 x 4 cells), the slabs given back.
    for _ in range(12):
        m.integrate_batch([_clearing(spec)])
    assert np.all(m.observed())
    assert m.held_cells() == spec.num_cells // 64
    assert m.state_nbytes() < once


def test_block_grid_round_trips_any_dense_state_and_risks_like_the_cell_grid() -> None:
    spec = SPEC_3D
    rng = np.random.default_rng(2)
    # Runs of equal rows with random breaks: some blocks uniform, some not.
    rows = rng.integers(0, 256, size=(5, 7), dtype=np.uint8)
    state = rows[np.minimum(np.cumsum(rng.random(spec.num_cells) < 0.004), 4)]
    observed = rng.random(spec.num_cells) < 0.5
    engine = FuzzyEngine.paper()
    grid = BlockGrid.from_dense(spec.shape, state, observed, rows[0], engine.defuzzify)
    dense = CellGrid(spec, state.copy(), observed, engine.defuzzify)
    np.testing.assert_array_equal(grid.dense(), state)
    np.testing.assert_array_equal(grid.observed(), observed)
    np.testing.assert_array_equal(grid.risk(), dense.risk())
    cells = rng.integers(0, spec.num_cells, 50)
    np.testing.assert_array_equal(grid.read(cells), state[cells])
    np.testing.assert_array_equal(grid.risk_of(cells), dense.risk_of(cells))
    assert grid.persistent_nbytes() < state.nbytes


def test_block_grid_refuses_states_that_do_not_fit() -> None:
    engine = FuzzyEngine.paper()
    n = SPEC_2D.num_cells
    with pytest.raises(ValueError, match="state"):
        BlockGrid.from_dense(SPEC_2D.shape, np.zeros((n - 1, 7), np.uint8), np.zeros(n, bool), np.zeros(7, np.uint8),
                             engine.defuzzify)
    with pytest.raises(ValueError, match="observed"):
        BlockGrid.from_dense(SPEC_2D.shape, np.zeros((n, 7), np.uint8), np.zeros(n, np.uint8), np.zeros(7, np.uint8),
                             engine.defuzzify)



def test_blocks_dropped_at_once_leave_the_index_as_dropping_them_one_at_a_time() -> None:
    from fuzzyocc._block_table import BlockIndex, insert

    rng = np.random.default_rng(5)
    coords = np.unique(rng.integers(-40, 40, (600, 3)), axis=0)
    one, many = BlockIndex(), BlockIndex()
    for index in (one, many):
        index.reserve(coords.shape[0])
        for s, (x, y, z) in enumerate(coords):
            insert(index.keys, index.slots, x, y, z, s)
        index.coords[: coords.shape[0]] = coords
        index.n = coords.shape[0]
    gone = np.sort(rng.choice(coords.shape[0], 250, replace=False))[::-1]
    moves = [(int(s), one.drop(int(s))) for s in gone]
    to, from_ = many.drop_many(gone)
    assert [(int(a), int(b)) for a, b in zip(to, from_)] == [(s, m) for s, m in moves if s != m]
    assert many.n == one.n == coords.shape[0] - 250 and many.dropped == one.dropped == 250
    assert np.array_equal(many.coords[: many.n], one.coords[: one.n])
    kept = one.coords[: one.n]
    assert np.array_equal(many.find(kept), np.arange(one.n)) and np.array_equal(one.find(kept), np.arange(one.n))
    assert np.all(many.find(coords[gone]) == -1)
