import dataclasses
import math

import numpy as np
import pytest

from fuzzyocc import BayesMap, FuzzyEngine, FuzzyMap, GridSpec, LaserScan, PointCloud, SensorModel
from fuzzyocc import bayes
from fuzzyocc.grid import RISK_STEP
from fuzzyocc.raycast import cast_rays

SPEC_2D = GridSpec(origin=(0.0, 0.0), size=(4.0, 2.0), resolution=0.1)  # 40 x 20 cells
SENSOR = SensorModel(range_sigma=0.03)
PAPER = FuzzyEngine.paper()  # floored at half a cell: sigma = 0.05 m here
POSE = (0.25, 1.05, 0.0)  # centre of cell (2, 10); beam 0 runs along row 10
ROW = 10


def _beam(ranges: list[float], range_max: float = 3.5, **kw: object) -> LaserScan:
    return LaserScan(pose=kw.pop("pose", POSE), angle_min=kw.pop("angle_min", 0.0),  # type: ignore[arg-type]
                     angle_increment=kw.pop("angle_increment", 0.01), ranges=ranges,  # type: ignore[arg-type]
                     range_min=0.1, range_max=range_max, **kw)  # type: ignore[arg-type]


def _same_arrays(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]) for k in a)


def _unknown_cells(m: FuzzyMap) -> np.ndarray:
    state = m.to_arrays()["state"]
    return np.all(state == m.engine.unknown_state(), axis=-1)


@pytest.mark.parametrize("factory", [FuzzyMap, BayesMap])
def test_a_hit_clears_the_cells_before_it_marks_its_cell_and_stops_past_the_occupied_region(factory) -> None:
    m = factory(SPEC_2D, SENSOR)
    m.integrate_batch([_beam([2.0])])  # surface at x = 2.25: the middle of cell 22
    risk, observed = m.risk(), m.observed()
    # Cell 23 (midpoint 2.35 m) is 2 sigmas past the surface, beyond the occupied region, which
    # ends 1.5 (fuzzy) or a few (Bayes) sigmas behind it: observed either way, updated by neither.
    last = 22 + math.floor(m.occupied_extent * 0.05 / 0.1 + 0.5)
    expected = np.zeros(SPEC_2D.shape, dtype=bool)
    expected[2 : last + 1, ROW] = True
    np.testing.assert_array_equal(observed, expected)
    assert risk[22, ROW] > 0.5
    assert np.all(risk[2:20, ROW] < 0.5)
    assert np.all(risk[~observed] == risk[0, 0])
    assert risk[0, 0] == pytest.approx(0.5, abs=1e-3)


def test_no_return_clears_free_space_up_to_range_max_and_marks_nothing_occupied() -> None:
    maps = {}
    for label, reading in [("inf", np.inf), ("range_max", 1.5), ("range_max+1", 2.5)]:
        m = FuzzyMap(SPEC_2D, SENSOR)
        m.integrate_batch([_beam([reading], range_max=1.5)])
        maps[label] = m
    m = maps["inf"]
    assert np.all(m.risk() <= 0.5)
    expected = np.zeros(SPEC_2D.shape, dtype=bool)
    expected[2:18, ROW] = True  # x from 0.25 to 1.75
    np.testing.assert_array_equal(m.observed(), expected)
    assert np.all(m.risk()[2:18, ROW] < 0.5)
    # Legacy drivers' no-return readings mean exactly the same thing.
    assert _same_arrays(maps["range_max"].to_arrays(), m.to_arrays())
    assert _same_arrays(maps["range_max+1"].to_arrays(), m.to_arrays())


def test_invalid_readings_are_skipped_and_counted() -> None:
    m = FuzzyMap(SPEC_2D, SENSOR)
    before = m.to_arrays()
    stats = m.integrate_scan(pose=POSE, angle_min=0.0, angle_increment=0.3, ranges=[-np.inf, np.nan, 0.05],
                             range_min=0.1, range_max=3.5)
    assert (stats.scans, stats.rays, stats.rays_skipped, stats.cells_updated) == (1, 0, 3, 0)
    after = m.to_arrays()
    assert after.pop("scans_fused") == 1
    before.pop("scans_fused")
    assert _same_arrays(before, after)


def test_stats_count_rays_updates_and_traversal() -> None:
    m = FuzzyMap(SPEC_2D, SENSOR)
    stats = m.integrate_batch([_beam([1.0, np.nan, -np.inf, 0.01, np.inf], angle_increment=0.4)])
    assert (stats.scans, stats.rays, stats.rays_skipped) == (1, 2, 3)
    # On a fresh map every cell given evidence leaves the unknown state.
    assert stats.cells_updated == int((~_unknown_cells(m)).sum())
    assert stats.cells_traversed >= int(m.observed().sum()) > stats.cells_updated > 0
    batch = m.integrate_batch([_beam([1.0]), _beam([2.0])])
    assert (batch.scans, batch.rays, m.scans_fused) == (2, 2, 3)


def _grazing_scan() -> list[LaserScan]:
    # Beam A ends in the middle of the wall cell C = (20, 10); beam B, 0.0222 rad below,
    # crosses C near its lower face and returns from 3.5 m: it says C is free.
    graze = -math.atan2(0.04, 1.8)
    return [_beam([3.5, 1.8], angle_min=graze, angle_increment=-graze)]


def test_a_thin_wall_survives_grazing_beams_of_the_same_scan() -> None:
    # The paper's engine: under the default one beam B (a no-return at range_max) never erodes a wall.
    together = FuzzyMap(SPEC_2D, SENSOR, PAPER)
    together.integrate_batch(_grazing_scan())
    alone = FuzzyMap(SPEC_2D, SENSOR, PAPER)
    alone.integrate_batch([_beam([1.8])])
    assert together.risk()[20, ROW] > 0.5
    assert together.risk()[20, ROW] == alone.risk()[20, ROW]
    # The same two beams as two scans: the free one erodes the wall.
    apart = FuzzyMap(SPEC_2D, SENSOR, PAPER)
    scan = _grazing_scan()[0]
    apart.integrate_batch([_beam([1.8]), _beam([3.5], angle_min=scan.angle_min)])
    assert apart.risk()[20, ROW] < alone.risk()[20, ROW]


@pytest.mark.parametrize("factory", [FuzzyMap, BayesMap])
def test_a_rejected_batch_leaves_the_map_bit_for_bit_unchanged(factory) -> None:
    m = factory(SPEC_2D, SENSOR)
    m.integrate_batch([_beam([2.0])])
    before = m.to_arrays()
    risk_before = m.risk().copy()
    good = _beam([1.0, 1.5], angle_increment=0.2)
    bad_batches = [
        ([good, "not a scan"], r"scans\[1\]"),
        ([good, PointCloud(points=[[1.0, 1.0, 1.0]], origin=(0.5, 0.5, 0.5), range_max=5.0)], r"scans\[1\]"),
    ]
    for batch, match in bad_batches:
        with pytest.raises(ValueError, match=match):
            m.integrate_batch(batch)
    with pytest.raises(ValueError, match="pose"):
        m.integrate_scan(pose=(np.nan, 0.0, 0.0), angle_min=0.0, angle_increment=0.1, ranges=[1.0],
                         range_min=0.1, range_max=3.0)
    with pytest.raises(ValueError, match="points"):
        m.integrate_points([[1.0, np.inf]], origin=(0.5, 0.5), range_max=3.0)
    assert _same_arrays(m.to_arrays(), before)
    np.testing.assert_array_equal(m.risk(), risk_before)


def test_a_batch_is_fused_in_order_like_successive_calls() -> None:
    scans = [_beam([2.0]), _beam([1.0])]  # cell 12 is free for the first, occupied for the second
    # The paper's engine: the default one counts evidence, and here both orders count the same.
    batched = FuzzyMap(SPEC_2D, SENSOR, PAPER)
    batched.integrate_batch(scans)
    one_by_one = FuzzyMap(SPEC_2D, SENSOR, PAPER)
    for scan in scans:
        one_by_one.integrate_batch([scan])
    assert _same_arrays(batched.to_arrays(), one_by_one.to_arrays())
    reordered = FuzzyMap(SPEC_2D, SENSOR, PAPER)
    reordered.integrate_batch(scans[::-1])
    assert not _same_arrays(batched.to_arrays(), reordered.to_arrays())


SPEC_3D = GridSpec(origin=(0.0, 0.0, 0.0), size=(3.0, 2.0, 2.0), resolution=0.1)


def test_point_cloud_into_a_3d_map() -> None:
    # Points in the middle of cells (20, 6..15, 6..15) of a wall, seen from (0.25, 1.05, 1.05).
    y, z = np.meshgrid(np.linspace(0.65, 1.55, 10), np.linspace(0.65, 1.55, 10))
    wall = np.stack([np.full(y.size, 2.05), y.ravel(), z.ravel()], axis=1)
    identity = [0.0, 0.0, 0.0, 1.0]
    cloud = PointCloud.from_sensor_frame(wall - [0.25, 1.05, 1.05], (0.25, 1.05, 1.05), identity, range_max=10.0)
    m = FuzzyMap(SPEC_3D, SENSOR)
    stats = m.integrate_batch([cloud])
    assert stats.rays == 100
    risk, observed = m.risk(), m.observed()
    assert risk.shape == SPEC_3D.shape
    assert np.all(risk[20, 6:16, 6:16] > 0.5)  # every wall cell a point fell in
    assert np.all(risk[3:18, 10, 10] < 0.5)  # the central beam's free space
    assert not observed[23:].any() and not observed[:, :, :3].any()
    with pytest.raises(ValueError, match="LaserScan"):
        m.integrate_batch([_beam([1.0])])


def test_points_beyond_range_max_clear_up_to_it_and_mark_nothing() -> None:
    m = FuzzyMap(SPEC_3D, SENSOR)
    m.integrate_points([[2.75, 1.05, 1.05]], origin=(0.25, 1.05, 1.05), range_max=1.0)
    expected = np.zeros(SPEC_3D.shape, dtype=bool)
    expected[2:13, 10, 10] = True  # x from 0.25 to 1.25
    np.testing.assert_array_equal(m.observed(), expected)
    assert np.all(m.risk()[2:13, 10, 10] < 0.5)
    assert np.all(m.risk() <= 0.5)


class _CountingEngine:
    """The paper's engine, counting the states it defuzzifies."""

    def __init__(self) -> None:
        self._engine = FuzzyEngine.paper()
        self.defuzzified = 0

    def __getattr__(self, name: str) -> object:
        return getattr(self._engine, name)

    def defuzzify(self, state: np.ndarray) -> np.ndarray:
        self.defuzzified += len(state)
        return self._engine.defuzzify(state)


def test_risk_is_recomputed_only_where_cells_changed() -> None:
    engine = _CountingEngine()
    m = FuzzyMap(SPEC_2D, SENSOR, engine=engine)  # type: ignore[arg-type]
    m.risk()
    start = engine.defuzzified
    first = m.integrate_batch([_beam([2.0])])
    first_risk = m.risk().copy()
    assert engine.defuzzified - start == first.cells_updated
    m.risk()
    m.risk_at([[1.0, 1.0]])
    assert engine.defuzzified - start == first.cells_updated  # nothing changed: nothing recomputed
    second = m.integrate_batch([_beam([1.0], pose=(0.25, 0.35, 0.0))])  # another row
    risk = m.risk()
    assert engine.defuzzified - start == first.cells_updated + second.cells_updated
    np.testing.assert_array_equal(risk[:, ROW], first_risk[:, ROW])
    assert np.any(risk[:, 3] != first_risk[:, 3])
    state = m.to_arrays()["state"].reshape(-1, 7)
    exact = FuzzyEngine.paper().defuzzify(state).astype(np.float64)
    # Cached in 16-bit fixed point: the nearest multiple of RISK_STEP to the engine's risk.
    assert np.all(np.abs(risk.ravel() - exact) <= RISK_STEP / 2)
    assert np.all(np.mod(risk.astype(np.float64), RISK_STEP) == 0.0)


def test_risk_and_observed_are_read_only_snapshots() -> None:
    m = FuzzyMap(SPEC_2D, SENSOR)
    with pytest.raises(ValueError):
        m.risk()[0, 0] = 1.0
    with pytest.raises(ValueError):
        m.observed()[0, 0] = True
    risk, observed = m.risk(), m.observed()
    m.integrate_batch([_beam([2.0])])
    assert np.all(risk == np.float32(0.5)) and not observed.any()  # what they were when read
    assert m.risk()[22, ROW] > 0.5 and m.observed()[22, ROW]


@pytest.mark.parametrize("factory", [FuzzyMap, BayesMap])
def test_unknown_is_exactly_one_half(factory) -> None:
    m = factory(SPEC_2D, SENSOR)
    assert m.risk().dtype == np.float32
    assert np.all(m.risk() == np.float32(0.5))
    m.integrate_batch([_beam([2.0])])
    assert np.all(m.risk()[~m.observed()] == np.float32(0.5))


@pytest.mark.parametrize("factory", [FuzzyMap, BayesMap])
def test_risk_does_not_depend_on_when_it_is_read(factory) -> None:
    # One map read after every scan, one only at the end: the same history, the same bits.
    scans = [_beam([2.0, 1.5, np.inf], angle_increment=0.2), _beam([1.2], pose=(3.5, 0.5, 2.5)),
             _beam([1.7], pose=(0.5, 0.5, 0.7)), _beam([2.0, 2.1], angle_increment=0.01)]
    eager, lazy = factory(SPEC_2D, SENSOR), factory(SPEC_2D, SENSOR)
    for scan in scans:
        eager.integrate_batch([scan])
        eager.risk()
        eager.risk_at([[2.25, 1.05]])
        lazy.integrate_batch([scan])
    assert eager.risk().tobytes() == lazy.risk().tobytes()
    assert eager.observed().tobytes() == lazy.observed().tobytes()


def test_observed_marks_exactly_the_cells_the_beams_reach_on_an_odd_sized_3d_grid() -> None:
    spec = GridSpec(origin=(0.0, 0.0, 0.0), size=(0.5, 0.3, 0.7), resolution=0.1)  # 105 cells: not whole bytes
    m = FuzzyMap(spec, SENSOR)
    pts = np.array([[0.45, 0.25, 0.65], [0.05, 0.25, 0.65], [0.45, 0.05, 0.05]])  # the last cell among others
    origin = np.array([0.05, 0.05, 0.05])
    m.integrate_points(pts, origin=origin, range_max=5.0)
    off = pts - origin
    dist = np.linalg.norm(off, axis=1)
    # The beams' segments without the occupied region behind the surface: reached whatever the model.
    reach = cast_rays(spec, np.repeat(origin[None], 3, axis=0), off / dist[:, None], dist,
                      measured=np.full(3, np.nan), sigma=np.ones(3), ray_offsets=np.array([0, 3]),
                      unknown_from=np.inf).cells
    observed = m.observed().ravel()
    assert observed[spec.num_cells - 1]
    assert np.all(observed[reach])
    assert observed.sum() <= reach.size + 3  # plus at most the occupied region past each surface


def test_risk_at_reads_the_cell_of_each_point_and_refuses_points_outside() -> None:
    m = FuzzyMap(SPEC_2D, SENSOR)
    m.integrate_batch([_beam([2.0])])
    pts = np.array([[2.25, 1.05], [1.0, 1.01], [0.0, 0.0], [3.99, 1.99]])
    got = m.risk_at(pts)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, m.risk()[[22, 10, 0, 39], [10, 10, 0, 19]])
    for bad in ([[4.0, 1.0]], [[-0.01, 1.0]], [[1.0, np.nan]], [[1.0, 1.0, 1.0]]):
        with pytest.raises(ValueError, match="points"):
            m.risk_at(bad)


def _two_scans(m: FuzzyMap | BayesMap) -> None:
    m.integrate_batch([_beam([2.0, 1.5, np.inf], angle_increment=0.2), _beam([1.2], pose=(3.5, 0.5, 2.5))])


@pytest.mark.parametrize("factory", [FuzzyMap, BayesMap])
def test_to_arrays_round_trip_bit_for_bit(factory) -> None:
    m = factory(SPEC_2D, SENSOR)
    _two_scans(m)
    arrays = m.to_arrays()
    restored = factory.from_arrays(SPEC_2D, SENSOR, arrays)
    assert restored.scans_fused == m.scans_fused == 2
    assert _same_arrays(restored.to_arrays(), arrays)
    np.testing.assert_array_equal(restored.risk(), m.risk())
    np.testing.assert_array_equal(restored.observed(), m.observed())
    # And they go on identically.
    for x in (m, restored):
        x.integrate_batch([_beam([1.7], pose=(0.5, 0.5, 0.7))])
    assert _same_arrays(restored.to_arrays(), m.to_arrays())


def test_from_arrays_refuses_arrays_that_do_not_fit() -> None:
    m = FuzzyMap(SPEC_2D, SENSOR)
    _two_scans(m)
    arrays = m.to_arrays()
    other = GridSpec(origin=(0.0, 0.0), size=(4.0, 2.1), resolution=0.1)
    with pytest.raises(ValueError, match="arrays"):
        FuzzyMap.from_arrays(other, SENSOR, arrays)
    with pytest.raises(ValueError, match="arrays"):
        BayesMap.from_arrays(SPEC_2D, SENSOR, arrays)
    with pytest.raises(ValueError, match="arrays"):
        FuzzyMap.from_arrays(SPEC_2D, SENSOR, {k: v for k, v in arrays.items() if k != "observed"})


def test_bayes_log_odds_are_clamped_like_octomap() -> None:
    m = BayesMap(SPEC_2D, SENSOR)
    m.integrate_batch([_beam([2.0])] * 40)
    logodds = m.to_arrays()["logodds"]
    assert logodds[22, ROW] == np.float32(bayes.CLAMP_MAX)
    assert np.all(logodds[2:18, ROW] == np.float32(bayes.CLAMP_MIN))
    assert logodds[0, 0] == 0.0
    np.testing.assert_allclose(m.risk()[22, ROW], bayes.probability(bayes.CLAMP_MAX), rtol=0, atol=RISK_STEP / 2)


def test_constructors_refuse_bad_arguments() -> None:
    with pytest.raises(ValueError, match="spec"):
        FuzzyMap((0.0, 0.0), SENSOR)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="sensor"):
        BayesMap(SPEC_2D, 0.03)  # type: ignore[arg-type]
    m = FuzzyMap(SPEC_2D)
    assert (m.model, m.sensor, m.spec) == ("fuzzy", SensorModel(), SPEC_2D)


def test_bayes_memory_accounting_counts_every_array_and_does_not_grow() -> None:
    spec = GridSpec(origin=(0.0, 0.0, 0.0), size=(1.0, 1.2, 0.5), resolution=0.1)  # 600 cells
    m = BayesMap(spec, SENSOR)
    n = spec.num_cells
    # Persistent: the cell states and one observed bit a cell; resident adds the 2-byte risk cache.
    assert m.state_nbytes() == 4 * n + n // 8
    assert m.resident_nbytes() == m.state_nbytes() + 2 * n
    before = (m.state_nbytes(), m.resident_nbytes())
    m.integrate_points([[0.9, 0.9, 0.25], [0.5, 1.1, 0.3]], origin=(0.1, 0.1, 0.25), range_max=5.0)
    m.risk()
    assert (m.state_nbytes(), m.resident_nbytes()) == before


def test_bayes_updates_every_cell_a_large_scan_clears() -> None:
    spec = GridSpec(origin=(0.0, 0.0), size=(20.0, 20.0), resolution=0.05)  # 160000 cells
    m = BayesMap(spec, SENSOR)
    angles = 2000
    m.integrate_scan(pose=(10.0, 10.0, 0.0), angle_min=-np.pi, angle_increment=2 * np.pi / angles,
                     ranges=np.full(angles, np.inf), range_min=0.1, range_max=9.0)
    observed = m.observed()
    assert observed.sum() > 100_000  # far more cells than one step of the update handles
    free = bayes.update_logodds(np.float32(0.0), bayes.logodds(bayes.opdf(-1e6, 1.0)))
    logodds = m.to_arrays()["logodds"]
    assert np.all(logodds[observed] == free)
    assert np.all(logodds[~observed] == 0.0)


@pytest.mark.parametrize("model", [FuzzyMap, BayesMap])
@pytest.mark.parametrize("ndim", [2, 3])
def test_a_batch_cast_in_chunks_gives_the_map_of_one_cast(model, ndim, monkeypatch) -> None:
    # a whole batch cast at once held an entry per (scan, cell): memory grew with the batch
    import fuzzyocc.maps as maps_module

    rng = np.random.default_rng(4)
    if ndim == 2:
        spec = GridSpec(origin=(0.0, 0.0), size=(6.0, 4.0), resolution=0.1)
        scans = [LaserScan(pose=(1.0 + 0.4 * k, 1.5 + 0.1 * k, 0.3 * k), angle_min=-1.5, angle_increment=0.05,
                           ranges=rng.uniform(0.5, 5.0, 61).tolist() + [math.inf], range_min=0.1, range_max=6.0)
                 for k in range(7)]
    else:
        spec = GridSpec(origin=(0.0, 0.0, 0.0), size=(4.0, 3.0, 2.0), resolution=0.1)
        scans = [PointCloud(points=rng.uniform((0.2, 0.2, 0.2), (3.8, 2.8, 1.8), (150, 3)),
                            origin=(2.0 + 0.1 * k, 1.5, 1.0), range_max=5.0) for k in range(7)]
    whole = model(spec, SensorModel(range_sigma=0.05))
    whole.integrate_batch(scans)
    assert len(whole._cast_chunks(scans)) == 1  # the default: one cast here
    monkeypatch.setattr(maps_module, "CAST_CHUNK_ENTRIES", 1)  # every scan a chunk of its own
    chunked = model(spec, SensorModel(range_sigma=0.05))
    assert chunked._cast_chunks(scans) == [(k, k + 1) for k in range(7)]
    stats = chunked.integrate_batch(scans)
    assert np.array_equal(chunked.risk(), whole.risk()) and np.array_equal(chunked.observed(), whole.observed())
    assert stats.scans == 7 and chunked.scans_fused == whole.scans_fused


def _awkward_scan(rng: np.random.Generator, n: int, k: int) -> LaserScan:
    """Hits, no-returns beside hits and in runs, and every kind of unusable reading, in random places."""
    ranges = rng.uniform(0.3, 4.5, n)
    kind = rng.integers(0, 8, n)
    ranges[kind == 0] = math.inf
    ranges[kind == 1] = 6.0  # range_max: a no-return too
    ranges[kind == 2] = math.nan
    ranges[kind == 3] = 0.01  # below range_min
    ranges[kind == 4] = -math.inf
    ranges[40:70] = math.inf  # a run of no-returns: cut only near its ends
    return LaserScan(pose=(3.0 + 0.2 * k, 2.0 - 0.1 * k, 0.4 * k), angle_min=-math.pi, angle_increment=2 * math.pi / n,
                     ranges=ranges, range_min=0.1, range_max=6.0)


@pytest.mark.parametrize("model", [FuzzyMap, BayesMap])
@pytest.mark.parametrize("ndim", [2, 3])
def test_a_scan_cast_in_parts_gives_the_map_of_one_cast(model, ndim, monkeypatch) -> None:
    # the rays of every beam of a scan were made at once (about 300 bytes a beam): two scans of
    # 2 M beams fused side by side took 1 GB; a huge scan is now made and cast a part at a time
    import fuzzyocc.maps as maps_module

    rng = np.random.default_rng(7)
    if ndim == 2:
        spec = GridSpec(origin=(0.0, 0.0), size=(6.0, 4.0), resolution=0.05)
        scans = [_awkward_scan(rng, 997, k) for k in range(3)]
    else:
        spec = GridSpec(origin=(0.0, 0.0, 0.0), size=(4.0, 3.0, 2.0), resolution=0.1)
        scans = [PointCloud(points=rng.uniform((0.2, 0.2, 0.2), (3.8, 2.8, 1.8), (400, 3)),
                            origin=(2.0 + 0.1 * k, 1.5, 1.0), range_max=2.5) for k in range(3)]
    whole = model(spec, SensorModel(range_sigma=0.05))
    expected = whole.integrate_batch(scans)
    monkeypatch.setattr(maps_module, "CAST_CHUNK_BEAMS", 50)  # parts of 50 beams: 20 or so a scan
    parted = model(spec, SensorModel(range_sigma=0.05))
    assert parted._cast_chunks(scans) == [(0, 1), (1, 2), (2, 3)]
    stats = parted.integrate_batch(scans)
    assert parted.to_arrays().keys() == whole.to_arrays().keys()
    for key, value in whole.to_arrays().items():
        assert np.array_equal(parted.to_arrays()[key], value), key
    assert np.array_equal(parted.risk(), whole.risk())
    assert stats == expected  # the same rays, dropped readings and cells walked


@pytest.mark.parametrize("usable", ["random", "at the ends only"])
def test_the_rays_of_a_scans_parts_are_the_rays_of_the_whole_scan(usable: str) -> None:
    # the parts read their neighbours across the cut: the incidence (one reading on each side) and the
    # no-returns cut at hits beside them (the engine's 3 usable readings on each side)
    scan = _awkward_scan(np.random.default_rng(3), 500, 1)
    if usable != "random":
        ranges = np.array(scan.ranges)
        ranges[2:-2] = math.nan
        ranges[0], ranges[-1] = math.inf, math.inf  # no-returns beside a hit: cut
        scan = dataclasses.replace(scan, ranges=ranges)
    m = FuzzyMap(GridSpec(origin=(0.0, 0.0), size=(6.0, 4.0), resolution=0.05))
    assert m.engine.no_return_neighbours and m.engine.incidence_floor < 1.0  # the default engine reads both
    whole = m._rays_of(scan)
    for size in (1, 2, 3, 7, 64, 499):
        parts = [m._rays_of(scan, slice(a, min(a + size, 500))) for a in range(0, 500, size)]
        for field in ("directions", "ranges", "hit", "incidence"):
            joined = np.concatenate([getattr(r, field) for r in parts])
            assert np.array_equal(joined, getattr(whole, field), equal_nan=field == "incidence"), (size, field)
        assert sum(r.skipped for r in parts) == whole.skipped


@pytest.mark.parametrize("usable", ["all", "at the ends only"])
def test_fusing_a_huge_scan_takes_memory_for_its_readings_not_for_its_rays(usable: str) -> None:
    # "at the ends only": every part's no-return cut reads the whole scan for its neighbours (
    # each of the 16 parts then made the whole scan's incidence, 10x the time and 200 MB)
    import tracemalloc

    spec = GridSpec(origin=(-10.0, -10.0), size=(20.0, 20.0), resolution=0.05)
    m = FuzzyMap(spec)
    beams = 1_000_000
    ranges = np.full(beams, 7.4)
    if usable != "all":
        ranges[3:-3] = math.nan
    scan = LaserScan(pose=(0.0, 0.0, 0.0), angle_min=-math.pi, angle_increment=2 * math.pi / beams,
                     ranges=ranges, range_min=0.05, range_max=30.0)
    m.integrate_batch([LaserScan(pose=(0.0, 0.0, 0.0), angle_min=-math.pi, angle_increment=0.1,
                                 ranges=np.full(63, 7.4), range_min=0.05, range_max=30.0)])  # kernels compiled
    tracemalloc.start()
    try:
        m.integrate_batch([scan])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # before: about 170 bytes a beam (rays of the whole scan, then their cast); now parts of 131,072 beams
    assert peak < 40 * beams, f"{peak / beams:.0f} bytes a beam"


@pytest.mark.parametrize("model", [FuzzyMap, BayesMap])
def test_a_map_is_freed_as_soon_as_it_is_let_go(model) -> None:
    # without the cyclic garbage collector: no reference cycle (a map's storage held a bound
    # method of the map, so a map let go lingered until the collector ran)
    import gc
    import weakref

    spec = GridSpec(origin=(0.0, 0.0), size=(4.0, 4.0), resolution=0.1)
    m = model(spec, SensorModel(range_sigma=0.05))
    m.integrate_scan(pose=(2.0, 2.0, 0.0), angle_min=-1.0, angle_increment=0.1, ranges=np.full(21, 1.5),
                     range_min=0.1, range_max=5.0)
    restored = model.from_arrays(spec, SensorModel(range_sigma=0.05), m.to_arrays())
    refs = [weakref.ref(m), weakref.ref(restored)]
    gc.collect()
    gc.disable()
    try:
        del m, restored
        assert [r() for r in refs] == [None, None]
    finally:
        gc.enable()


def test_beam_angles_past_float_range_are_refused_before_any_cast() -> None:
    # a scan whose last beam's angle overflowed to inf cast NaN directions; the kernel then handed out cell ids
    # it never wrote and the service segfaulted, at every restart too
    with pytest.raises(ValueError, match="angles"):
        LaserScan(pose=(0.0, 0.0, 0.0), angle_min=0.0, angle_increment=1e308, ranges=[1.0] * 5000, range_min=0.1,
                  range_max=10.0)
    spec = GridSpec(origin=(0.0, 0.0), size=(2.0, 2.0), resolution=0.1)
    with pytest.raises(ValueError, match="finite"):
        cast_rays(spec, np.array([[1.0, 1.0]]), np.array([[np.nan, 0.0]]), t_end=np.array([1.0]),
                  measured=np.array([0.5]), sigma=np.array([0.05]), ray_offsets=np.array([0, 1]), unknown_from=1.5)


@pytest.mark.parametrize("dims", [2, 3])
def test_a_fixed_maps_snapshot_holds_its_blocks_and_restores_it_bit_for_bit(dims: int) -> None:
    # a snapshot costs what the map holds: its blocks, not every cell of its box
    if dims == 2:
        spec = GridSpec(origin=(-20.0, -20.0), size=(40.0, 40.0), resolution=0.05)
        scans = [LaserScan(pose=(0.1 * k, 0.0, 0.3 * k), angle_min=-1.0, angle_increment=0.01,
                           ranges=np.full(201, 3.0), range_min=0.1, range_max=10.0) for k in range(5)]
    else:
        spec = GridSpec(origin=(-10.0, -10.0, -2.0), size=(20.0, 20.0, 4.0), resolution=0.1)
        rng = np.random.default_rng(3)
        scans = [PointCloud(points=rng.uniform(-3.0, 3.0, (500, 3)), origin=(0.0, 0.0, 0.0), range_max=10.0)]
    live = FuzzyMap(spec, SensorModel())
    live.integrate_batch(scans)
    snapshot = live.snapshot_arrays()
    assert "state" not in snapshot and snapshot["slabs"].nbytes < live.to_arrays()["state"].nbytes / 10
    restored = FuzzyMap.from_arrays(spec, SensorModel(), snapshot)
    for key, value in live.to_arrays().items():
        assert restored.to_arrays()[key].tobytes() == value.tobytes(), key
    # and both go on alike
    more = scans[:1]
    live.integrate_batch(more)
    restored.integrate_batch(more)
    assert restored.risk().tobytes() == live.risk().tobytes() and restored.scans_fused == live.scans_fused
