"""Map quality against OctoMap, CI-sized: the instrument, and the targets on the smallest recorded log.

The instrument tests check what ``bench/bench_maps.py`` measures with: the held-out scoring on
hand-made numbers, our march and OctoMap's ``castRay`` on a synthetic wall and against each other
on a real log, the dynamic-obstacle case's local OctoMap copy against a full copy of the tree, and
the plan audit's clearance. The target test runs ``bench maps --quick`` on orebro (its first 120
scans): our default engine's figures and OctoMap's, computed in the same test, compared as
relations, never times.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench import _dynamic, _logmaps, _plan_audit, bench_maps
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan
from fuzzyocc.presets import DEFAULT_PRESET, preset
from tests.conftest import carmen_log

RES = 0.05


def orebro() -> Path:
    """The smallest recorded log (237 scans), from tests/data; the test fails, not skips, without it."""
    return carmen_log("orebro-corrected.log.gz")


@pytest.fixture(scope="module")
def orebro_subset():  # type: ignore[no-untyped-def]
    """The CI-sized case: orebro's first 120 scans, their grid, split, held-out beams and OctoMap tree."""
    scans = _logmaps.load(orebro())[: bench_maps.QUICK_SCANS]
    spec = _logmaps.grid_for(scans)
    fused, held = _logmaps.split(scans)
    tree = _logmaps.octomap_tree(spec, fused)
    return spec, fused, _logmaps.held_out_beams(held), tree, _logmaps.octomap_occupied(tree, spec)


# ------------------------------------------------------------------ the scoring
def test_score_counts_within_early_late_and_none() -> None:
    measured = np.ones(7)
    # within (exact, 1.6 cells long, exactly 2 cells short), 10 cells early, 20 late, two with no surface
    predicted = np.array([1.0, 1.08, 0.9, 0.5, 2.0, np.inf, np.inf])
    s = _logmaps.score(predicted, measured, RES)
    assert s.beams == 7
    assert (s.within, s.early, s.late, s.none) == pytest.approx((3 / 7, 1 / 7, 1 / 7, 2 / 7))
    assert s.median_error == pytest.approx(0.5)  # sorted: 0, .08, .1, .5, 1, inf, inf
    assert math.isinf(_logmaps.score(np.array([1.0, np.inf, np.inf]), np.ones(3), RES).median_error)


# ------------------------------------------------------------------ the marches
def _wall_scans(poses: list[tuple[float, float, float]], wall_x: float, half_fov: float) -> list[LaserScan]:
    """Scans of a straight wall at ``x = wall_x`` (across the whole map), 0.5 degree beams."""
    n = int(round(2 * half_fov / math.radians(0.5))) + 1
    inc = 2 * half_fov / (n - 1)
    out = []
    for x, y, theta in poses:
        angles = theta - half_fov + inc * np.arange(n)
        out.append(LaserScan(pose=(x, y, theta), angle_min=-half_fov, angle_increment=inc,
                             ranges=(wall_x - x) / np.cos(angles), range_min=0.01, range_max=10.0))
    return out


def test_our_march_and_octomap_castray_find_a_known_wall() -> None:
    spec = GridSpec(origin=(0.0, 0.0), size=(4.0, 4.0), resolution=RES)
    wall_x = 3.01  # inside the cells from x = 3.0, so every beam ends in the same column
    tree = _logmaps.octomap_tree(spec, _wall_scans([(1.0, 1.5, 0.0), (1.0, 2.0, 0.0), (1.0, 2.5, 0.0)], wall_x, 0.6))
    held = _wall_scans([(1.3, 1.8, 0.1)], wall_x, 0.5)[0]
    beams = _logmaps.held_out_beams([held])
    truth = beams.ranges
    risk = np.zeros(spec.shape, np.float32)
    risk[int(round(3.0 / RES)):, :] = 1.0  # the wall's cells, known
    ours = _logmaps.predicted_ranges(risk, spec, beams)
    theirs = _logmaps.octomap_predicted(tree, spec, beams)
    assert beams.ranges.size > 100
    assert np.all(np.abs(ours - truth) <= RES), np.max(np.abs(ours - truth))
    assert np.all(np.abs(theirs - truth) <= RES), np.max(np.abs(theirs - truth))
    s = _logmaps.score(ours, truth, RES)
    assert (s.within, s.early, s.late, s.none) == (1.0, 0.0, 0.0, 0.0)


def test_our_march_on_octomaps_occupied_cells_is_castray(orebro_subset) -> None:  # type: ignore[no-untyped-def]
    """Marching OctoMap's occupied cells (``octomap_occupied``) gives ``castRay``'s answer on a real log."""
    spec, _, beams, tree, occupied = orebro_subset
    cast = _logmaps.octomap_predicted(tree, spec, beams)
    marched = _logmaps.predicted_ranges(occupied.astype(np.float32), spec, beams, threshold=0.5)
    assert np.array_equal(np.isfinite(cast), np.isfinite(marched))
    assert np.isfinite(cast).mean() > 0.9
    both = np.isfinite(cast)
    assert np.allclose(cast[both], marched[both], atol=1e-5)  # OctoMap's coordinates are float32


# ------------------------------------------------------------------ the dynamic obstacle
def test_the_box_is_read_at_its_near_face() -> None:
    scan = LaserScan(pose=(0.5, 1.0, 0.0), angle_min=-0.5, angle_increment=0.01, ranges=np.full(101, np.inf),
                     range_min=0.01, range_max=30.0)
    lo, hi = np.array([1.5, 0.8]), np.array([1.9, 1.2])
    boxed, beams, no_returns = _dynamic.with_box(scan, lo, hi)
    angles = -0.5 + 0.01 * np.arange(101)
    crossing = np.abs(np.tan(angles)) <= 0.2 / 1.0  # through the near face, 1 m ahead, 0.4 m wide
    assert beams == no_returns == crossing.sum() > 3  # every beam of this scan was a no-return
    assert np.allclose(boxed.ranges[crossing], 1.0 / np.cos(angles[crossing]))
    assert np.all(np.isinf(boxed.ranges[~crossing]))


def test_a_copied_map_is_a_restored_one_and_independent(orebro_subset) -> None:  # type: ignore[no-untyped-def]
    spec, fused, _, _, _ = orebro_subset
    for trained in (FuzzyMap(spec, engine=preset(DEFAULT_PRESET)), BayesMap(spec)):
        _logmaps.fuse(trained, fused[:60])
        before = np.array(trained.risk())
        copied = _dynamic.copy_map(trained)
        if isinstance(trained, FuzzyMap):
            restored = FuzzyMap.from_arrays(spec, trained.sensor, trained.to_arrays(), trained.engine)
        else:
            restored = BayesMap.from_arrays(spec, trained.sensor, trained.to_arrays())
        _logmaps.fuse(copied, fused[60:])
        _logmaps.fuse(restored, fused[60:])
        a, b = copied.to_arrays(), restored.to_arrays()
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
        assert np.array_equal(copied.risk(), restored.risk())
        assert np.array_equal(trained.risk(), before) and trained.scans_fused == 60


def test_dynamic_trials_with_a_local_octomap_equal_a_full_copy(orebro_subset) -> None:  # type: ignore[no-untyped-def]
    spec, fused, _, tree, occupied = orebro_subset
    fuzzy, bayes = FuzzyMap(spec, engine=preset(DEFAULT_PRESET)), BayesMap(spec)
    _logmaps.fuse(fuzzy, fused)
    _logmaps.fuse(bayes, fused)
    local = _dynamic.run_trials(fused, spec, fuzzy, bayes, tree, occupied, trials=3)
    full = _dynamic.run_trials(fused, spec, fuzzy, bayes, tree, occupied, trials=3, octomap_full_copy=True)
    assert len(local) == 3 and local == full
    for t in local:
        assert t.beams >= 3 and t.cells > 0
        assert t.seen["OctoMap"]  # 3 hits outweigh a free cell's clamped log-odds
        assert 0 < t.scans_to_clear["OctoMap"] <= _dynamic.CAP


# ------------------------------------------------------------------ the plan audit
def test_clearance_is_measured_from_cell_centres_along_a_densified_path() -> None:
    spec = GridSpec(origin=(0.0, 0.0), size=(5.0, 5.0), resolution=RES)
    occupied = np.zeros(spec.shape, dtype=bool)
    occupied[40, :] = True  # a wall in the cells x in [2.0, 2.05)
    clearance = _plan_audit.clearance_map(occupied, RES)
    assert _plan_audit.path_clearance(np.array([[1.01, 0.5], [1.01, 4.5]]), spec, clearance) == pytest.approx(1.0)
    # two far-apart vertices: only the densified path crosses the wall
    assert _plan_audit.path_clearance(np.array([[1.0, 0.5], [3.0, 4.5]]), spec, clearance) == 0.0
    ok = _plan_audit.PlanCheck(0, "grid", (0, 0), (1, 1), 1.0, "exact", 1.0,
                               _plan_audit.path_clearance(np.array([[1.87, 0.5], [1.87, 4.5]]), spec, clearance))
    near = _plan_audit.PlanCheck(0, "grid", (0, 0), (1, 1), 1.0, "exact", 1.0,
                                 _plan_audit.path_clearance(np.array([[1.92, 0.5], [1.92, 4.5]]), spec, clearance))
    assert ok.clearance == pytest.approx(0.15) and ok.clear(RES)  # radius 0.2 m less a cell
    assert near.clearance == pytest.approx(0.10) and not near.clear(RES)


def test_plan_pairs_are_driven_poses_far_apart() -> None:
    spec = GridSpec(origin=(0.0, 0.0), size=(10.0, 10.0), resolution=RES)
    poses = np.column_stack([np.linspace(0.5, 9.5, 50), np.full(50, 5.0)])
    valid = np.ones(spec.shape, dtype=bool)
    valid[int(0.5 / RES), int(5.0 / RES)] = False  # the first pose is not free
    pairs = _plan_audit.pick_pairs(poses, valid, spec, pairs=3)
    far = 0.3 * math.hypot(10.0, 10.0)
    assert len(pairs) == 3 and all(np.hypot(*(poses[j] - poses[i])) >= far for i, j in pairs)
    assert pairs == _plan_audit.pick_pairs(poses, valid, spec, pairs=3)
    assert all(i != 0 and j != 0 for i, j in pairs)


# ------------------------------------------------------------------ the targets
@pytest.fixture(scope="module")
def orebro_report() -> bench_maps.LogReport:
    """The map-quality figures of ``bench maps`` on orebro's first 120 scans: ours (the default preset) and OctoMap in the same run."""
    return bench_maps.evaluate_log(orebro(), DEFAULT_PRESET, scan_limit=bench_maps.QUICK_SCANS,
                                   trials=bench_maps.QUICK_TRIALS, pairs=bench_maps.QUICK_PAIRS,
                                   reproducible_plans=True)  # RRTstar on an iteration count: the same paths under load


def test_default_engine_predicts_held_out_beams_and_clears_obstacles_as_well_as_octomap(
    orebro_report: bench_maps.LogReport,
) -> None:
    rep = orebro_report
    ours, octo = rep.scores["FuzzyMap"], rep.scores["OctoMap"]
    unmet = []
    if not ours.within >= octo.within:
        unmet.append(f"within 2 cells {ours.within:.3f} < OctoMap's {octo.within:.3f}")
    if not ours.none <= octo.none + 0.01:
        unmet.append(f"no surface {ours.none:.3f} > OctoMap's {octo.none:.3f} + 0.01")
    if not ours.early <= octo.early + 0.02:
        unmet.append(f"too early {ours.early:.3f} > OctoMap's {octo.early:.3f} + 0.02")
    if not ours.median_error <= octo.median_error:
        unmet.append(f"median error {ours.median_error:.4f} m > OctoMap's {octo.median_error:.4f} m")
    assert rep.trials, "no obstacle could be placed"
    for t in rep.trials:
        if t.seen["OctoMap"] and not t.seen["FuzzyMap"]:
            unmet.append(f"obstacle at scan {t.scan_index}: OctoMap marked it, ours did not")
        if t.scans_to_clear["FuzzyMap"] > t.scans_to_clear["OctoMap"]:
            unmet.append(f"obstacle at scan {t.scan_index}: cleared in {t.scans_to_clear['FuzzyMap']} scans, "
                         f"OctoMap in {t.scans_to_clear['OctoMap']}")
    assert not unmet, "; ".join(unmet)
    verdicts = {t.name: t.met for t in bench_maps.targets(rep)}
    assert all(met for name, met in verdicts.items() if "plan" not in name), verdicts  # the bench agrees


# raises: a crash of the bench is a failure, not the expected shortfall
@pytest.mark.xfail(strict=True, raises=AssertionError, reason="the plan audit on the CI-sized map (orebro's first "
                   "120 scans) is not met: paths pass a cell OctoMap still holds occupied and our map has cleared "
                   "(bench/README.md); on the full logs it is")
def test_default_engine_plans_keep_clear_of_octomaps_occupied_cells(orebro_report: bench_maps.LogReport) -> None:
    rep = orebro_report
    paths = [c for c in rep.plans if c.has_path]
    assert paths, "no plan to audit"
    floor = _plan_audit.ROBOT_RADIUS - rep.resolution
    unmet = [f"{c.planner} plan {c.pair}: {c.clearance:.2f} m from an OctoMap-occupied cell (< {floor:.2f})"
             for c in paths if not c.clear(rep.resolution)]
    assert not unmet, "; ".join(unmet)
