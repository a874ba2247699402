"""The default engine ``evidence``: levels of evidence a user can read off the risk."""

import math

import numpy as np
import pytest

from fuzzyocc import FuzzyMap, GridSpec, LaserScan, SensorModel, presets
from fuzzyocc.evidence import evidence_engine

ENGINE = evidence_engine()
SPEC = GridSpec(origin=(0.0, 0.0), size=(4.0, 2.0), resolution=0.05)
FAR_FREE = np.array([-20.0])  # a cell well in front of the measured surface, in sigmas


def _levels(distances: list[float]) -> float:
    """Risk of a new cell after fusing the given evidence (distances in sigmas), in order."""
    state = ENGINE.unknown_state()[None, :]
    for d in distances:
        state = ENGINE.fuse(state, ENGINE.fuzzify(np.array([d])))
    return float(ENGINE.defuzzify(state)[0])


def test_it_is_the_default_preset_of_maps_and_the_service() -> None:
    assert presets.DEFAULT_PRESET == "evidence" and FuzzyMap(SPEC).engine == ENGINE
    assert ENGINE.num_labels == 11 and ENGINE.and_op == "min" and ENGINE.or_op == "max"


def test_free_space_gains_a_tenth_of_risk_a_reading_down_to_its_floor() -> None:
    free = [-20.0] * 6
    assert [round(_levels(free[:k]), 3) for k in range(7)] == [0.5, 0.4, 0.3, 0.2, 0.1, 0.033, 0.033]


def test_a_surface_is_refused_by_a_default_plan_after_one_reading() -> None:
    once, twice = _levels([0.0]), _levels([0.0, 0.0])
    assert 0.6 < once < twice < 0.95 and _levels([0.0] * 4) > 0.95


@pytest.mark.parametrize("where", [0.0, 0.5])  # sigmas from the measured surface
def test_an_obstacle_seen_three_times_is_cleared_by_the_fifth_free_reading(where: float) -> None:
    risks = [_levels([where] * 3 + [-20.0] * k) for k in range(1, 6)]
    assert all(r >= 0.6 for r in risks[:3]) and risks[4] < 0.6  # OctoMap's defaults need seven


def test_a_no_return_beside_hits_stops_before_them_and_one_in_open_space_clears_to_range_max() -> None:
    ranges = np.array([3.0, 3.0, 3.0, np.inf, 3.2, 3.1, np.inf, np.inf, np.inf, np.inf, np.inf, np.inf, np.inf])
    scan = LaserScan(pose=(0.0, 0.0, 0.0), angle_min=-0.06, angle_increment=0.01, ranges=ranges,
                     range_min=0.1, range_max=20.0)
    rays = scan.to_rays().cut_no_returns(ENGINE.no_return_neighbours)
    assert rays.ranges[3] == pytest.approx(2.9)  # a dark spot in a wall: free up to 0.1 m before it
    assert rays.ranges[6] == pytest.approx(20.0)  # hits on one side only: the edge of open space
    assert np.all(rays.ranges[7:] == 20.0) and not rays.hit[3]
    assert scan.to_rays().cut_no_returns(0).ranges[3] == 20.0


def test_a_wall_with_a_dark_spot_survives_and_an_obstacle_that_left_open_space_is_cleared() -> None:
    spec = GridSpec(origin=(0.0, -2.0), size=(8.0, 4.0), resolution=0.05)
    angles = np.radians(np.arange(-20.0, 20.5, 0.5))
    wall = 3.0 / np.cos(angles)
    dark = wall.copy()
    dark[40] = np.inf  # the beam straight ahead returns nothing from the wall
    m = FuzzyMap(spec)
    scan = dict(pose=(0.0, 0.0, 0.0), angle_min=float(angles[0]), angle_increment=float(angles[1] - angles[0]),
                range_min=0.1, range_max=30.0)
    for _ in range(3):
        m.integrate_scan(ranges=wall, **scan)
    for _ in range(10):
        m.integrate_scan(ranges=dark, **scan)
    assert m.risk_at([[3.025, 0.0]])[0] > 0.9  # the wall cell behind the dark spot
    gone = np.full_like(wall, np.inf)  # the "wall" was an obstacle: it left open space behind
    risks = []
    for _ in range(6):
        m.integrate_scan(ranges=gone, **scan)
        risks.append(float(m.risk_at([[3.025, 0.0]])[0]))
    assert risks[2] >= 0.6 > risks[-1]


def test_the_cell_in_front_of_the_surface_is_not_marked_occupied() -> None:
    m = FuzzyMap(SPEC, SensorModel(range_sigma=0.03))
    for _ in range(3):
        m.integrate_scan(pose=(0.0, 1.025, 0.0), angle_min=0.0, angle_increment=0.0, ranges=[3.025],
                         range_min=0.1, range_max=10.0)
    risk = m.risk()[:, 20]
    assert risk[60] > 0.9 and risk[59] < 0.5 and np.all(risk[:59] < 0.5)  # the wall cell and only it


def _wall_scan(x: float, y: float, wall_x: float, angles: np.ndarray) -> LaserScan:
    ranges = (wall_x - x) / np.cos(angles)
    return LaserScan(pose=(x, y, 0.0), angle_min=float(angles[0]), angle_increment=float(angles[1] - angles[0]),
                     ranges=ranges, range_min=0.1, range_max=30.0)


def test_the_incidence_of_each_beam_is_estimated_from_its_neighbours() -> None:
    angles = np.radians(np.arange(-80.0, 80.5, 0.5))
    rays = _wall_scan(0.0, 1.0, 2.0, angles).to_rays(incidence=True)
    head_on, grazing = rays.incidence[160], rays.incidence[2]  # 0 and -79 degrees from the wall's normal
    assert head_on == pytest.approx(1.0, abs=1e-6)
    assert grazing == pytest.approx(math.cos(math.radians(79.0)), abs=1e-3)
    assert np.isnan(rays.incidence[0]) and np.isnan(rays.incidence[-1])  # edges: no neighbour on one side
