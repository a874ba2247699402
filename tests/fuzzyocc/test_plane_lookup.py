"""``OccupancyMap.plane_lookup``: a 2-D map's cells through a table of risk codes, rows along y, in one pass."""

from __future__ import annotations

import numpy as np
import pytest

from fuzzyocc import BayesMap, FuzzyMap, GridSpec
from fuzzyocc.grid import RISK_CODES, RISK_STEP


def _mapped(model: type[FuzzyMap] | type[BayesMap], spec: GridSpec) -> FuzzyMap | BayesMap:
    m = model(spec)
    rng = np.random.default_rng(3)
    for k in range(4):
        n = 720
        m.integrate_scan(pose=(rng.uniform(-1, 1), rng.uniform(-1, 1), 0.4 * k), angle_min=-3.1,
                         angle_increment=6.2 / n, ranges=rng.uniform(0.5, 4.0, n), range_min=0.1, range_max=3.5)
    return m


@pytest.mark.parametrize("model", [FuzzyMap, BayesMap])
@pytest.mark.parametrize("shape_m", [(9.0, 6.0), (6.05, 9.35)])  # whole blocks, and partial ones at the edges
def test_each_cell_is_its_risk_code_looked_up_and_unobserved_cells_are_marked(
        model: type[FuzzyMap] | type[BayesMap], shape_m: tuple[float, float]) -> None:
    spec = GridSpec(origin=(-4.0, -3.5), size=shape_m, resolution=0.05)
    m = _mapped(model, spec)
    lut = np.random.default_rng(5).integers(-100, 101, RISK_CODES).astype(np.int8)  # any table, not a monotone one
    got = m.plane_lookup(lut, -7)
    codes = np.rint(m.risk() / RISK_STEP).astype(np.int64)  # exact: risk is code * RISK_STEP
    want = np.where(m.observed(), lut[codes], -7).T  # rows along y
    assert got.shape == (spec.shape[1], spec.shape[0]) and got.dtype == np.int8
    assert np.array_equal(got, want)
    assert 0 < (got != -7).sum() < got.size  # the history observed some cells, not all


def test_a_3d_map_and_a_short_table_are_refused() -> None:
    solid = FuzzyMap(GridSpec(origin=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0), resolution=0.1))
    with pytest.raises(ValueError, match="2-D"):
        solid.plane_lookup(np.zeros(RISK_CODES, np.int8), -1)
    flat = FuzzyMap(GridSpec(origin=(0.0, 0.0), size=(1.0, 1.0), resolution=0.1))
    with pytest.raises(ValueError, match="65536 entries"):
        flat.plane_lookup(np.zeros(256, np.int8), -1)
