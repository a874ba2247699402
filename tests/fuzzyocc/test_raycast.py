import itertools

import numpy as np
import pytest

from fuzzyocc.config import GridSpec
from fuzzyocc.keys import flat_to_keys
from fuzzyocc._block_table import BlockIndex
from fuzzyocc import raycast
from fuzzyocc.raycast import (
    NO_RETURN_DISTANCE,
    WINDOW_LIMIT,
    Lattice,
    cast_into,
    cast_rays,
    cross_into,
    traversal_cells,
)


def _slab(lo: np.ndarray, hi: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[float, float]:
    """Parameters where the line o + t d enters and leaves the box [lo, hi] (empty: enter > leave)."""
    enter, leave = -np.inf, np.inf
    for a in range(o.size):
        if d[a] == 0.0:
            if not lo[a] <= o[a] <= hi[a]:
                return np.inf, -np.inf
            continue
        ta, tb = sorted(((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]))
        enter, leave = max(enter, ta), min(leave, tb)
    return enter, leave


def _reference(spec: GridSpec, o: np.ndarray, d: np.ndarray, t_end: float) -> dict[tuple[int, ...], tuple[float, float]]:
    """Brute force over every cell: overlap of the segment [0, t_end] with it, and the line's chord midpoint."""
    out = {}
    origin = np.asarray(spec.origin)
    for key in itertools.product(*(range(n) for n in spec.shape)):
        lo = origin + np.asarray(key) * spec.resolution
        enter, leave = _slab(lo, lo + spec.resolution, o, d)
        if enter > leave:
            continue
        overlap = min(leave, t_end) - max(enter, 0.0)
        out[key] = (overlap, 0.5 * (enter + leave))
    return out


def _one_ray_per_scan(spec: GridSpec, origins: np.ndarray, dirs: np.ndarray, t_end: np.ndarray):
    n = len(origins)
    return cast_rays(spec, origins, dirs, t_end, measured=np.zeros(n), sigma=np.ones(n),
                     ray_offsets=np.arange(n + 1), unknown_from=np.inf)


@pytest.mark.parametrize(
    "spec",
    [
        GridSpec(origin=(-0.3, 0.7), size=(2.1, 1.5), resolution=0.3),
        GridSpec(origin=(0.2, -0.4, 0.1), size=(1.2, 1.0, 0.8), resolution=0.2),
    ],
    ids=["2d", "3d"],
)
def test_traversal_is_exact_against_brute_force(spec: GridSpec) -> None:
    rng = np.random.default_rng(11)
    n = 150
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    # Origins inside and outside the box; directions and lengths so rays start, end and pass anywhere.
    origins = lo - 0.5 + rng.random((n, spec.ndim)) * (hi - lo + 1.0)
    dirs = rng.normal(size=(n, spec.ndim))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t_end = rng.random(n) * 3.0
    res = _one_ray_per_scan(spec, origins, dirs, t_end)
    checked = 0
    for r in range(n):
        # With measured range 0 and sigma 1 the evidence is the chord midpoint: it orders the cells along the ray.
        mids = res.distance_sigmas[res.scan_offsets[r]:res.scan_offsets[r + 1]]
        got = res.cells[res.scan_offsets[r]:res.scan_offsets[r + 1]][np.argsort(mids, kind="stable")]
        mids = np.sort(mids)
        keys = [tuple(k) for k in flat_to_keys(spec, got)]
        assert res.cells_traversed[r] == len(keys), "a cell was visited twice"
        ref = _reference(spec, origins[r], dirs[r], t_end[r])
        must = {k for k, (overlap, _) in ref.items() if overlap > 1e-9}
        may = {k for k, (overlap, _) in ref.items() if overlap > -1e-9}
        assert must <= set(keys), "a cell crossed by the segment was skipped"
        assert set(keys) <= may, "a cell off the segment was visited"
        # Along the ray, each cell shares a face with the previous one.
        steps = np.abs(np.diff(np.array(keys).reshape(-1, spec.ndim), axis=0)).sum(axis=1)
        assert np.all(steps == 1)
        for k, m in zip(keys, mids):
            assert m == pytest.approx(ref[k][1], abs=1e-5)
        checked += len(must) > 0
    assert checked > n // 4  # the random rays really cross the map


def test_axis_aligned_ray_from_outside_is_clipped_and_includes_the_end_cell() -> None:
    spec = GridSpec(origin=(0.0, 0.0), size=(1.0, 0.5), resolution=0.1)
    res = _one_ray_per_scan(spec, np.array([[-2.0, 0.25]]), np.array([[1.0, 0.0]]), np.array([2.55]))
    keys = flat_to_keys(spec, res.cells)
    assert keys.tolist() == [[i, 2] for i in range(6)]  # x from 0 to 0.55: cells 0..5
    np.testing.assert_allclose(res.distance_sigmas, 2.0 + 0.05 + 0.1 * np.arange(6), rtol=1e-6)


def test_ray_that_misses_the_map_reaches_nothing() -> None:
    spec = GridSpec(origin=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0), resolution=0.25)
    res = _one_ray_per_scan(spec, np.array([[-1.0, 2.0, 0.5], [0.5, 0.5, 0.5]]),
                            np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.array([5.0, 0.0]))
    assert res.scan_offsets.tolist() == [0, 0, 0]


def test_the_work_estimate_counts_each_segment_clipped_to_the_map() -> None:
    spec = GridSpec(origin=(0.0, 0.0), size=(1.0, 0.5), resolution=0.1)
    # from outside, along x through the whole map: 10 cells of length, plus the first cell
    assert traversal_cells(spec, np.array([-2.0, 0.25]), np.array([[3.0, 0.25]])) == 11
    # along an axis beside the map (parallel to y, outside x), and a segment ending before it: nothing
    assert traversal_cells(spec, np.array([-1.0, 0.25]), np.array([[-1.0, 3.0], [-0.5, 0.25]])) == 0
    # inside, parallel to x: a quarter of the way (2.5 cells -> 3) plus the first cell
    assert traversal_cells(spec, np.array([0.3, 0.25]), np.array([[0.55, 0.25]])) == 4
    # a diagonal inside: its L1 length in cells (2 + 2) plus the first cell
    assert traversal_cells(spec, np.array([0.05, 0.05]), np.array([[0.25, 0.25]])) == 5
    # segments add up
    assert traversal_cells(spec, np.array([-2.0, 0.25]), np.array([[3.0, 0.25]] * 3)) == 33


@pytest.mark.parametrize("ndim", [2, 3])
def test_the_work_estimate_is_within_a_few_cells_a_segment_of_what_the_cast_walks(ndim: int) -> None:
    # sensors inside and outside the box, segments leaving it or missing it, some parallel to an axis: a
    # segment of L1 length L cells crosses between L - ndim and L cell boundaries; the estimate is L + 1
    spec = GridSpec(origin=(0.0,) * ndim, size=(2.0,) * ndim, resolution=0.1)
    rng = np.random.default_rng(7)
    inside = 0
    for _ in range(300):
        origin = rng.uniform(-1.0, 3.0, ndim)
        direction = rng.normal(size=ndim)
        direction[0] *= rng.random() < 0.8  # parallel to the first axis's slabs, now and then
        direction /= np.linalg.norm(direction)
        length = rng.uniform(0.05, 4.0)
        estimate = traversal_cells(spec, origin, (origin + direction * length)[None])
        walked = cast_rays(spec, origin[None], direction[None], t_end=np.array([length]), measured=np.array([length]),
                           sigma=np.array([0.1]), ray_offsets=np.array([0, 1]), unknown_from=0.0).cells_traversed
        assert -2 <= estimate - walked <= ndim + 1, (origin, direction, length, estimate, walked)
        inside += walked > 0
    assert 50 < inside < 300  # segments in the map and out of it were tried


def _two_beams_through_one_cell(measured: np.ndarray, unknown_from: float, offsets: list[int]):
    spec = GridSpec(origin=(0.0, 0.0), size=(1.0, 1.0), resolution=0.1)
    origins = np.array([[0.05, 0.55], [0.55, 0.05]])
    dirs = np.array([[1.0, 0.0], [0.0, 1.0]])  # both cross cell (5, 5)
    return spec, cast_rays(spec, origins, dirs, t_end=np.array([0.9, 0.9]), measured=measured,
                           sigma=np.array([0.1, 0.1]), ray_offsets=np.array(offsets), unknown_from=unknown_from)


def test_a_cell_reached_by_several_beams_of_a_scan_keeps_the_most_occupied_evidence() -> None:
    spec, res = _two_beams_through_one_cell(np.array([0.5, 0.9]), np.inf, [0, 2])
    cells = res.cells.tolist()
    assert len(cells) == len(set(cells)) and res.cells_traversed[0] == 20
    shared = cells.index(5 * 10 + 5)
    # Beam 1 crosses the cell 0.0 m from its measured surface, beam 2 0.4 m in front of it.
    assert res.distance_sigmas[shared] == pytest.approx(0.0, abs=1e-6)


def test_scans_are_deduplicated_apart() -> None:
    _, res = _two_beams_through_one_cell(np.array([0.5, 0.9]), np.inf, [0, 1, 2])
    assert res.scan_offsets.tolist() == [0, 10, 20]
    second = res.cells[10:].tolist().index(55) + 10
    assert res.distance_sigmas[second] == pytest.approx(-4.0, abs=1e-5)


def test_evidence_past_unknown_from_counts_only_when_no_beam_brings_more() -> None:
    # Beam 1 measured at 0.2 m: the shared cell (0.5 m) is 3 sigmas behind its surface.
    _, alone = _two_beams_through_one_cell(np.array([0.2, 0.9]), 1.5, [0, 1, 2])
    assert alone.distance_sigmas[alone.cells[:10].tolist().index(55)] == -np.inf
    _, both = _two_beams_through_one_cell(np.array([0.2, 0.9]), 1.5, [0, 2])
    assert both.distance_sigmas[both.cells.tolist().index(55)] == pytest.approx(-4.0, abs=1e-5)


def test_no_return_beams_mark_free_space() -> None:
    spec = GridSpec(origin=(0.0, 0.0), size=(2.0, 2.0), resolution=0.1)
    res = cast_rays(spec, np.array([[1.05, 1.05]] * 2), np.array([[1.0, 0.0], [0.0, -1.0]]),
                    t_end=np.array([0.5, 0.5]), measured=np.array([np.nan, np.nan]), sigma=np.array([0.1, 0.1]),
                    ray_offsets=np.array([0, 2]), unknown_from=1.5)
    assert res.cells.size == 11  # the sensor's cell is shared by both beams
    assert np.all(res.distance_sigmas == np.float32(NO_RETURN_DISTANCE))



@pytest.mark.parametrize(
    "spec",
    [
        GridSpec(origin=(0.0, 0.0, 0.0), size=(10.0, 10.0, 2.0), resolution=0.05),  # few cells reached: sorted
        GridSpec(origin=(0.0, 0.0), size=(5.0, 5.0), resolution=0.05),  # most cells reached: swept
    ],
    ids=["sparse", "dense"],
)
def test_each_scan_of_a_batch_gets_the_union_of_its_beams_with_their_largest_evidence(spec: GridSpec) -> None:
    rng = np.random.default_rng(5)
    offsets = np.array([0, 40, 100, 250, 600])  # growing scans: buffers grow between and within them
    n = offsets[-1]
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    origins = lo + rng.random((n, spec.ndim)) * (hi - lo)
    dirs = rng.normal(size=(n, spec.ndim))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t_end = rng.uniform(1.0, 8.0, n)
    measured = np.where(rng.random(n) < 0.3, np.nan, t_end - 0.1)
    sigma = np.full(n, 0.05)
    batch = cast_rays(spec, origins, dirs, t_end, measured, sigma, offsets, unknown_from=1.5)
    beams = cast_rays(spec, origins, dirs, t_end, measured, sigma, np.arange(n + 1), unknown_from=1.5)
    reached = np.diff(batch.scan_offsets)
    assert reached.max() > 4 * 1024  # more than the kernel's first buffers hold
    for s in range(len(offsets) - 1):
        cells = batch.cells[batch.scan_offsets[s]:batch.scan_offsets[s + 1]]
        dist = batch.distance_sigmas[batch.scan_offsets[s]:batch.scan_offsets[s + 1]]
        lo_b, hi_b = beams.scan_offsets[offsets[s]], beams.scan_offsets[offsets[s + 1]]
        want = np.full(spec.num_cells, np.nan, dtype=np.float32)
        np.fmax.at(want, beams.cells[lo_b:hi_b], beams.distance_sigmas[lo_b:hi_b])
        np.testing.assert_array_equal(cells, np.flatnonzero(~np.isnan(want)))  # each once, increasing
        np.testing.assert_array_equal(dist, want[cells])


@pytest.mark.parametrize(
    ("spec", "block_shift"),
    [
        (GridSpec(origin=(0.0, 0.0, 0.0), size=(3.3, 2.9, 1.3), resolution=0.1), (2, 2, 2)),
        (GridSpec(origin=(0.0, 0.0, 0.0), size=(1.3, 0.9, 0.5), resolution=0.1), (2, 1, 3)),
        (GridSpec(origin=(0.0, 0.0), size=(3.7, 2.1), resolution=0.1), (3, 3, 0)),
    ],
    ids=["3d", "3d-uneven", "2d"],
)
def test_block_keys_reach_the_same_cells_with_the_same_evidence(spec: GridSpec, block_shift) -> None:
    rng = np.random.default_rng(11)
    n = 300
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    origins = lo + rng.random((n, spec.ndim)) * (hi - lo)
    dirs = rng.normal(size=(n, spec.ndim))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t_end = rng.uniform(0.5, 4.0, n)
    measured = np.where(rng.random(n) < 0.3, np.nan, t_end - 0.1)
    args = (origins, dirs, t_end, measured, np.full(n, 0.05), np.array([0, 100, n]))
    flat = cast_rays(spec, *args, unknown_from=1.5)
    index = BlockIndex(capacity=2)  # full at once: the cast stops, the index grows, the cast goes on
    blocks = cast_into(Lattice.of(spec), index, block_shift, *args, unknown_from=1.5)
    np.testing.assert_array_equal(blocks.scan_offsets, flat.scan_offsets)
    np.testing.assert_array_equal(blocks.cells_traversed, flat.cells_traversed)
    # The cell of key ``slot << bits | offset``, by the documented formula.
    sh = np.asarray(block_shift)
    bits = int(sh.sum())
    slot, offset = blocks.cells >> bits, blocks.cells & ((1 << bits) - 1)
    inner = np.stack(np.unravel_index(offset, tuple(1 << sh)), axis=1)
    cells = (index.coords[slot].astype(np.int64) << sh) + inner
    shape = (*spec.shape, 1)[:3]
    for s in range(2):
        part = slice(flat.scan_offsets[s], flat.scan_offsets[s + 1])
        got = np.ravel_multi_index(tuple(cells[part].T), shape)
        order = np.argsort(got)
        np.testing.assert_array_equal(got[order], flat.cells[part])  # each once
        np.testing.assert_array_equal(blocks.distance_sigmas[part][order], flat.distance_sigmas[part])
        # a block's cells come together: each block starts one run
        runs = np.count_nonzero(np.diff(slot[part]) != 0) + 1
        assert runs == np.unique(slot[part]).size
    assert index.n == np.unique(slot).size  # the index holds the blocks reached, no other
    # A scan too wide for a dense window of its blocks finds them in the hash alone: the same keys.
    hashed = cast_into(Lattice.of(spec), BlockIndex(capacity=2), block_shift, *args, unknown_from=1.5, window_limit=0)
    np.testing.assert_array_equal(hashed.cells, blocks.cells)
    np.testing.assert_array_equal(hashed.distance_sigmas, blocks.distance_sigmas)
    with pytest.raises(ValueError, match="shift"):
        cast_into(Lattice.of(spec), index, (1, 1), *args, unknown_from=1.5)


def _lattice_cells(index: BlockIndex, keys: np.ndarray, shift: tuple[int, int, int]) -> np.ndarray:
    """Lattice coordinates (n, 3) of cast keys ``slot << bits | offset``."""
    sh = np.asarray(shift)
    bits = int(sh.sum())
    inner = np.stack(np.unravel_index(keys & ((1 << bits) - 1), tuple(1 << sh)), axis=1)
    return (index.coords[keys >> bits].astype(np.int64) << sh) + inner


@pytest.mark.parametrize("ndim", [2, 3])
def test_the_unbounded_lattice_reaches_what_a_box_at_the_origin_reaches(ndim: int) -> None:
    # A growing map's lattice starts at the frame's origin; a fixed box with its corner there numbers the same
    # cells by the same arithmetic, for rays inside it.
    rng = np.random.default_rng(4)
    n = 400
    origins = rng.uniform(6.0, 10.0, (n, ndim))
    dirs = rng.normal(size=(n, ndim))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t_end = rng.uniform(0.5, 5.0, n)
    measured = np.where(rng.random(n) < 0.3, np.nan, t_end - 0.1)
    args = (origins, dirs, t_end, measured, np.full(n, 0.05), np.array([0, 150, n]))
    shift = (2, 2, 2 if ndim == 3 else 0)
    index = BlockIndex()
    grown = cast_into(Lattice((0.0,) * ndim, 0.1, None), index, shift, *args, unknown_from=1.5)
    hashed = cast_into(Lattice((0.0,) * ndim, 0.1, None), BlockIndex(), shift, *args, unknown_from=1.5, window_limit=0)
    np.testing.assert_array_equal(hashed.cells, grown.cells)
    np.testing.assert_array_equal(hashed.distance_sigmas, grown.distance_sigmas)
    box = GridSpec(origin=(0.0,) * ndim, size=(16.0,) * ndim, resolution=0.1)
    fixed = cast_rays(box, *args, unknown_from=1.5)
    got = np.ravel_multi_index(tuple(_lattice_cells(index, grown.cells, shift)[:, :ndim].T), box.shape)
    np.testing.assert_array_equal(grown.scan_offsets, fixed.scan_offsets)
    for s in range(2):
        part = slice(fixed.scan_offsets[s], fixed.scan_offsets[s + 1])
        order = np.argsort(got[part])
        np.testing.assert_array_equal(got[part][order], fixed.cells[part])
        np.testing.assert_array_equal(grown.distance_sigmas[part][order], fixed.distance_sigmas[part])


@pytest.mark.parametrize("ndim", [2, 3])
def test_the_unbounded_lattice_walks_exactly_across_negative_coordinates(ndim: int) -> None:
    rng = np.random.default_rng(8)
    spec = GridSpec(origin=(-1.2,) * ndim, size=(2.4,) * ndim, resolution=0.3)  # the reference's cells
    shift = (2, 2, 2 if ndim == 3 else 0)
    for _ in range(40):
        o = rng.uniform(-0.5, 0.5, ndim)
        d = rng.normal(size=ndim)
        d /= np.linalg.norm(d)
        index = BlockIndex()
        cast = cast_into(Lattice((0.0,) * ndim, 0.3, None), index, shift, o[None], d[None], np.array([0.6]),
                         np.zeros(1), np.ones(1), np.array([0, 1]), unknown_from=np.inf)
        keys = {tuple(int(v) + 4 for v in c[:ndim]) for c in _lattice_cells(index, cast.cells, shift)}
        ref = _reference(spec, o, d, 0.6)
        assert {k for k, (overlap, _) in ref.items() if overlap > 1e-9} <= keys
        assert keys <= {k for k, (overlap, _) in ref.items() if overlap > -1e-9}


def test_the_work_estimate_never_overflows_into_a_small_number() -> None:
    # one beam of a range_max near the largest float made the sum of its coordinates inf, and
    # the compiled estimate wrapped to a negative count that let any batch through its budget
    spec = GridSpec(origin=(0.0, 0.0), size=(1.0, 1.0), resolution=0.1)
    far = np.array([[1.5e308 * 0.7, 1.5e308 * 0.7]])
    assert traversal_cells(spec, np.array([0.05, 0.05]), far) == 20  # inside the box: 9.5 + 9.5 cells, plus the first
    for bad in ([np.inf, 0.05], [np.nan, 0.5], [-np.inf, np.inf]):  # more than any budget, never less
        assert traversal_cells(spec, np.array([0.05, 0.05]), np.array([bad])) >= 2**62


def _entered(index: BlockIndex) -> set[tuple[int, ...]]:
    return {tuple(int(v) for v in row) for row in index.coords[: index.n]}


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("bounded", [True, False], ids=["box", "lattice"])
@pytest.mark.parametrize("window", [WINDOW_LIMIT, 0], ids=["dense", "cast"])
def test_the_cells_rays_cross_are_the_cells_the_cast_reaches(ndim: int, bounded: bool, window: int,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    # what a batch's allocation bound counts: the same cells as the fusion's cast walks, each once, over several
    # calls into one index (the blocks of a batch's scans), rays from inside, outside and across the box alike
    monkeypatch.setattr(raycast, "WINDOW_LIMIT", window)  # 0: every call too wide for the dense marks, so cast
    rng = np.random.default_rng(11 + ndim)
    lattice = Lattice((-1.0,) * ndim, 0.25, (24,) * ndim if bounded else None)
    crossed, cast = BlockIndex(), BlockIndex()
    for _ in range(3):
        n = 300
        origins = rng.uniform(-3.0, 6.0, (n, ndim))
        dirs = rng.normal(size=(n, ndim))
        dirs[rng.random(n) < 0.2, 0] = 0.0  # along a face's plane: ties between the axes
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        t_end = rng.uniform(0.1, 8.0, n)
        cross_into(lattice, crossed, origins, dirs, t_end)
        cast_into(lattice, cast, (0, 0, 0), origins, dirs, t_end, np.full(n, np.nan), np.ones(n), np.array([0, n]),
                  unknown_from=np.inf, split=False)
        assert crossed.n == cast.n and _entered(crossed) == _entered(cast)
    assert cast.n > 100
