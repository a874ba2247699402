import numpy as np
import pytest

from fuzzyocc.config import GridSpec
from fuzzyocc.keys import coords_to_keys, flat_to_keys, keys_to_coords, keys_to_flat

SPEC_2D = GridSpec(origin=(-1.0, 2.0), size=(2.0, 1.0), resolution=0.25)  # 8 x 4 cells
SPEC_3D = GridSpec(origin=(0.0, 0.0, -0.5), size=(1.0, 0.5, 1.0), resolution=0.1)


def test_points_land_in_the_half_open_cell_that_contains_them() -> None:
    keys, valid = coords_to_keys(SPEC_2D, [[-1.0, 2.0], [-0.76, 2.24], [-0.75, 2.25], [0.99, 2.99]])
    assert valid.all()
    assert keys.tolist() == [[0, 0], [0, 0], [1, 1], [7, 3]]


def test_points_outside_are_masked_and_clipped_never_wrapped() -> None:
    pts = [[-1.01, 2.5], [1.0, 2.5], [0.0, 3.0], [0.0, 1.9], [50.0, -50.0]]
    keys, valid = coords_to_keys(SPEC_2D, pts)
    assert not valid.any()
    # Clipped to the nearest cell: a wrapped -1 would read the far edge instead.
    assert keys.tolist() == [[0, 2], [7, 2], [4, 3], [4, 0], [7, 0]]


def test_non_finite_points_are_invalid() -> None:
    _, valid = coords_to_keys(SPEC_2D, [[np.nan, 2.5], [0.0, np.inf], [-np.inf, 2.5], [0.0, 2.5]])
    assert valid.tolist() == [False, False, False, True]


def test_wrong_shape_raises_naming_points() -> None:
    with pytest.raises(ValueError, match="points"):
        coords_to_keys(SPEC_2D, [[0.0, 2.5, 1.0]])
    with pytest.raises(ValueError, match="points"):
        coords_to_keys(SPEC_3D, [0.0, 0.1, 0.2])


def test_cell_centres_round_trip_in_3d() -> None:
    rng = np.random.default_rng(3)
    keys = np.stack([rng.integers(0, n, 50) for n in SPEC_3D.shape], axis=1)
    centres = keys_to_coords(SPEC_3D, keys)
    np.testing.assert_allclose(centres[0], np.asarray(SPEC_3D.origin) + (keys[0] + 0.5) * 0.1)
    back, valid = coords_to_keys(SPEC_3D, centres)
    assert valid.all()
    np.testing.assert_array_equal(back, keys)


def test_flat_ids_follow_c_order_of_the_shape_and_round_trip() -> None:
    keys = np.array([[0, 0], [0, 1], [1, 0], [7, 3]])
    flat = keys_to_flat(SPEC_2D, keys)
    assert flat.tolist() == [0, 1, 4, 31]
    np.testing.assert_array_equal(flat_to_keys(SPEC_2D, flat), keys)
    with pytest.raises(ValueError):
        keys_to_flat(SPEC_2D, np.array([[8, 0]]))
