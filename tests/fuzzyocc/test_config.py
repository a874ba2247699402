"""GridSpec and SensorModel refuse what would make a map meaningless, before any work."""

from __future__ import annotations

import pytest

from fuzzyocc import GridSpec, SensorModel
from fuzzyocc.config import MAX_COORDINATE_M, MAX_SIGMA_M


@pytest.mark.parametrize(("origin", "size"), [
    ((1e300, 0.0), (10.0, 10.0)),  # every cell centre would be the same float
    ((MAX_COORDINATE_M - 5.0, 0.0), (10.0, 10.0)),  # its far side is beyond the bound
    ((0.0, -2e7), (10.0, 10.0)),
])  # fmt: skip
def test_a_box_far_from_the_frames_origin_is_refused(origin, size) -> None:
    with pytest.raises(ValueError, match="use a local map frame"):
        GridSpec(origin=origin, size=size, resolution=0.05)


def test_utm_sized_coordinates_are_accepted() -> None:
    spec = GridSpec(origin=(500_000.0, 5_000_000.0), size=(20.0, 10.0), resolution=0.05)
    assert spec.shape == (400, 200) and spec.upper == pytest.approx((500_020.0, 5_000_010.0))


def test_a_cell_count_that_would_overflow_is_refused_with_the_limit() -> None:
    with pytest.raises(ValueError, match="more than the limit of 64000000"):
        GridSpec(origin=(0.0, 0.0), size=(1e6, 1e6), resolution=1e-300)


@pytest.mark.parametrize(("field", "value"), [("range_sigma", 1e308), ("registration_sigma", MAX_SIGMA_M * 1.01),
                                              ("range_sigma_per_m", 2.0), ("range_sigma", -0.01)])
def test_sensor_sigmas_beyond_their_bounds_are_refused_naming_the_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=f"^{field} must be a number in"):
        SensorModel(**{field: value})


def test_sensor_sigmas_at_their_bounds_are_accepted() -> None:
    sensor = SensorModel(range_sigma=MAX_SIGMA_M, registration_sigma=MAX_SIGMA_M, range_sigma_per_m=1.0)
    assert sensor.range_sigma == MAX_SIGMA_M


@pytest.mark.parametrize("resolution", [0.05, 0.1, 0.03, 1 / 3, 0.123456789, 0.05000001])
def test_the_built_size_gives_the_same_shape_again(resolution: float) -> None:
    # a client copies a map by sending the size GET /maps/{name} shows (built_size): the copy must have its cells
    for n in [1, 7, 302, 8101, 200_006, 399_999]:
        spec = GridSpec(origin=(0.0, 0.0), size=((n - 0.5) * resolution, resolution), resolution=resolution,
                        max_cells=10**6)
        again = GridSpec(origin=(0.0, 0.0), size=spec.built_size, resolution=resolution, max_cells=10**6)
        assert spec.shape == again.shape == (n, 1), (resolution, n, spec.built_size)


def test_the_built_size_is_written_short_where_that_keeps_the_shape() -> None:
    spec = GridSpec(origin=(0.0, 0.0), size=(0.29, 15.99), resolution=0.1)
    assert spec.shape == (3, 160) and spec.built_size == (0.3, 16.0)  # 3 * 0.1 is 0.30000000000000004
