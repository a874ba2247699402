import numpy as np
import pytest

from fuzzyocc.reserved import Reserved


def test_a_longer_view_keeps_what_the_shorter_one_held_without_a_copy() -> None:
    slabs = Reserved(np.uint16, (4, 3), rows=1000)
    short = slabs.view(10)
    short[:] = np.arange(120, dtype=np.uint16).reshape(10, 4, 3)
    longer = slabs.view(500)
    assert np.shares_memory(short, longer)
    assert np.array_equal(longer[:10], short)
    longer[499] = 7  # every row reserved is writable
    assert slabs.view(500)[499, 0, 0] == 7
    with pytest.raises(ValueError, match="1000 are reserved"):
        slabs.view(1001)


def test_released_rows_are_given_back_and_read_as_zeros_the_rows_before_kept() -> None:
    slabs = Reserved(np.uint8, (4096,), rows=64)  # a row a page
    full = slabs.view(64)
    full[:] = 9
    slabs.release_from(16)
    assert np.all(slabs.view(64)[16:] == 0)
    assert np.all(slabs.view(16) == 9)


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_a_map_copied_or_pickled_keeps_its_cells_and_grows_apart_from_the_original(how: str) -> None:
    import copy
    import pickle

    from fuzzyocc import FuzzyMap, LatticeSpec, PointCloud, SensorModel

    rng = np.random.default_rng(4)
    clouds = [PointCloud(points=rng.uniform(-6.0, 6.0, (4000, 3)), origin=(0.3 * k, 0.0, 0.0), range_max=8.0)
              for k in range(3)]
    original = FuzzyMap(LatticeSpec(3, 0.1), SensorModel(range_sigma=0.05))
    original.integrate_batch(clouds[:1])
    copied = copy.deepcopy(original) if how == "deepcopy" else pickle.loads(pickle.dumps(original))
    for m in (original, copied):  # both pools grow past what they held when copied
        m.integrate_batch(clouds[1:])
    fresh = FuzzyMap(LatticeSpec(3, 0.1), SensorModel(range_sigma=0.05))
    fresh.integrate_batch(clouds[:1])
    fresh.integrate_batch(clouds[1:])
    for m in (original, copied):
        for key, value in fresh.to_arrays().items():
            assert np.array_equal(m.to_arrays()[key], value), key
