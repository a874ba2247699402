"""RiskField: input checks, the footprint rule, dilation, unknown space, pickling."""

from __future__ import annotations

import itertools
import pickle

import numpy as np
import pytest
from scipy import ndimage

from planning import RiskField
from planning.field import DEFAULT_MAX_RISK, footprint

RES = 0.05


def _boundary(n: int = 41) -> np.ndarray:
    s = np.linspace(0.0, 1.0, n)
    zero, one = np.zeros(n), np.ones(n)
    return np.concatenate([np.stack(e, 1) for e in ((s, zero), (s, one), (zero, s), (one, s))])


def _squares_overlap_disk(offset: tuple[int, int], radius_cells: float) -> bool:
    """Brute force: some point of the centre cell and some point of the offset cell are closer
    than the radius. The closest points of two squares lie on their boundaries, sampled here
    (with the corners and matching edge coordinates, so the sampled minimum is exact)."""
    a = _boundary()
    b = a + np.asarray(offset, dtype=float)
    d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).min()
    return offset == (0, 0) or d < radius_cells


@pytest.mark.parametrize("radius_cells", [0.0, 0.7, 1.3, 2.5, 4.0, 5.6])
def test_footprint_holds_every_cell_the_disk_can_overlap_from_anywhere_in_the_cell(radius_cells: float) -> None:
    fp = footprint(radius_cells * RES, RES, 2)
    m = fp.shape[0] // 2
    for i, j in itertools.product(range(-m, m + 1), repeat=2):
        assert fp[i + m, j + m] == _squares_overlap_disk((i, j), radius_cells), (i, j)


def test_zero_radius_dilates_nothing() -> None:
    risk = np.random.default_rng(0).random((30, 20)).astype(np.float32)
    field = RiskField(risk, RES, (0.0, 0.0))
    assert np.array_equal(field.dilated_risk(0.0), risk)


@pytest.mark.parametrize("ndim", [2, 3])
def test_dilated_risk_is_the_maximum_under_the_footprint(ndim: int) -> None:
    shape = (40, 30) if ndim == 2 else (20, 18, 12)
    risk = np.random.default_rng(1).random(shape).astype(np.float32)
    field = RiskField(risk, RES, (0.0,) * ndim)
    fp = footprint(0.17, RES, ndim)
    expected = ndimage.grey_dilation(risk, footprint=fp, mode="constant", cval=0.5)
    assert np.array_equal(field.dilated_risk(0.17), expected)


def test_dilated_risk_bounds_the_true_footprint_risk_anywhere_in_a_cell(request: pytest.FixtureRequest) -> None:
    rng = np.random.default_rng(2)
    risk = (rng.random((60, 60)) ** 8).astype(np.float32)
    field = RiskField(risk, RES, (-1.0, 2.0))
    radius = 0.13
    worst = request.getfixturevalue("footprint_check")
    dilated = field.dilated_risk(radius)
    pts = np.asarray(field.origin) + rng.uniform(0.3, 2.7, size=(2000, 2))
    idx, inside = field.cell_of(pts)
    assert inside.all()
    for p, (i, j) in zip(pts, idx, strict=True):
        assert worst(field, p[None, :], radius) <= dilated[i, j]


def test_unknown_space_is_dilated_and_the_outside_of_the_map_is_unknown() -> None:
    observed = np.ones((40, 40), dtype=bool)
    observed[20, 20] = False
    field = RiskField(np.zeros((40, 40), np.float32), RES, (0.0, 0.0), observed=observed)
    unknown = field.dilated_unknown(0.1)  # 2 cells: gap < 2 cells
    assert unknown[20, 20] and unknown[22, 20] and unknown[20, 18] and unknown[21, 21]
    assert not unknown[23, 20] and not unknown[20, 17] and not unknown[23, 23]
    assert unknown[0, 10] and unknown[39, 10]  # the footprint leaves the map
    assert not unknown[10, 10]
    # and the risk outside the map is 0.5
    assert field.dilated_risk(0.1)[0, 10] == pytest.approx(0.5)


def test_valid_mask_combines_max_risk_and_unknown_space() -> None:
    risk = np.zeros((30, 30), np.float32)
    risk[5, 5] = 0.7
    observed = np.ones((30, 30), dtype=bool)
    observed[20, 20] = False
    field = RiskField(risk, RES, (0.0, 0.0), observed=observed)
    allow = field.valid_mask(0.0, 0.6, allow_unknown=True)
    forbid = field.valid_mask(0.0, 0.6, allow_unknown=False)
    assert not allow[5, 5] and allow[20, 20]
    assert not forbid[5, 5] and not forbid[20, 20]
    assert field.valid_mask(0.0, 0.7)[5, 5]


def test_max_risk_bounds_what_was_observed_and_allow_unknown_what_was_not() -> None:
    # a surface hit once and seen through twice is an observed cell at 0.5; with max_risk 0.6 the
    # planner drove past it 0.10 m away (infinite-corridor), where OctoMap holds it occupied
    risk = np.full((30, 30), 0.4, np.float32)  # one net level of free evidence
    risk[10, 10] = 0.5  # observed: evidence for and against that cancels out
    risk[20, 20] = 0.5  # never observed
    observed = np.ones((30, 30), dtype=bool)
    observed[20, 20] = False
    field = RiskField(risk, RES, (0.0, 0.0), observed=observed)
    default = field.valid_mask(0.0, DEFAULT_MAX_RISK)
    assert DEFAULT_MAX_RISK == 0.45 and default[5, 5] and not default[10, 10] and default[20, 20]
    assert not field.valid_mask(0.0, DEFAULT_MAX_RISK, allow_unknown=False)[20, 20]
    # allow_unknown decides never-observed space whatever max_risk: before, max_risk below 0.5 shut it too
    strict = field.valid_mask(0.0, 0.3)
    assert not strict[5, 5] and strict[20, 20]
    # the footprint carries both: a robot 2 cells away from the observed 0.5 cell is not valid at 0.1 m
    dilated = field.valid_mask(0.1, DEFAULT_MAX_RISK)
    assert not dilated[12, 10] and dilated[13, 10] and dilated[22, 20]


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"risk": np.full((4, 4), np.nan)}, "risk"),
        ({"risk": np.full((4, 4), 1.5)}, "risk"),
        ({"risk": np.zeros(5)}, "risk"),
        ({"risk": np.zeros((2, 2, 2, 2))}, "risk"),
        ({"risk": "not an array"}, "risk"),
        ({"resolution": 0.0}, "resolution"),
        ({"resolution": -0.1}, "resolution"),
        ({"resolution": float("nan")}, "resolution"),
        ({"origin": (0.0,)}, "origin"),
        ({"origin": (0.0, float("inf"))}, "origin"),
        ({"observed": np.ones((3, 4), bool)}, "observed"),
        ({"observed": np.ones((4, 4), np.uint8)}, "observed"),
    ],
)
def test_bad_input_raises_value_error_naming_the_field(kwargs: dict, name: str) -> None:
    args = {"risk": np.zeros((4, 4)), "resolution": RES, "origin": (0.0, 0.0), "observed": None} | kwargs
    with pytest.raises(ValueError, match=rf"^{name}:"):
        RiskField(**args)


def test_bad_radius_or_max_risk_raise_value_error_naming_them() -> None:
    field = RiskField(np.zeros((4, 4)), RES, (0.0, 0.0))
    with pytest.raises(ValueError, match="^robot_radius:"):
        field.dilated_risk(-0.1)
    with pytest.raises(ValueError, match="^max_risk:"):
        field.valid_mask(0.1, 1.2)


def test_field_copies_its_input_and_is_read_only() -> None:
    risk = np.zeros((5, 5), np.float32)
    field = RiskField(risk, RES, (0.0, 0.0))
    risk[2, 2] = 1.0
    assert field.risk[2, 2] == 0.0
    with pytest.raises(ValueError):
        field.risk[1, 1] = 0.5
    with pytest.raises(ValueError):
        field.dilated_risk(0.1)[1, 1] = 0.5


def test_cell_of_is_half_open_at_the_upper_bound() -> None:
    field = RiskField(np.zeros((10, 4)), 0.5, (1.0, -1.0))
    idx, inside = field.cell_of(np.array([[1.0, -1.0], [5.99, 0.99], [6.0, 0.0], [0.99, 0.0]]))
    assert inside.tolist() == [True, True, False, False]
    assert idx[:2].tolist() == [[0, 0], [9, 3]]


def test_field_pickles_without_its_cache() -> None:
    field = RiskField(np.random.default_rng(3).random((50, 50)), RES, (0.5, -0.5), observed=np.ones((50, 50), bool))
    before = len(pickle.dumps(field))
    field.dilated_risk(0.2)
    field.dilated_unknown(0.2)
    data = pickle.dumps(field)
    assert len(data) == before
    back = pickle.loads(data)
    assert np.array_equal(back.risk, field.risk) and np.array_equal(back.observed, field.observed)
    assert back.origin == field.origin and back.resolution == field.resolution
    assert np.array_equal(back.dilated_risk(0.2), field.dilated_risk(0.2))
