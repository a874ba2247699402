"""The compiled kernels against brute force and against OMPL."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ompl import base as ob
from scipy import sparse
from scipy.sparse import csgraph

from planning import RiskField, _dubins_kernels, _segment_kernels
from planning.grid_search import grid_path
from planning.packed import PackedGrid

RES = 0.1
ORIGIN = (1.0, -2.0)


@pytest.fixture(scope="module")
def packed() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(5)
    risk = rng.random((50, 40)).astype(np.float32)
    valid = rng.random((50, 40)) > 0.03
    return risk, valid, _segment_kernels.pack(risk, valid, ORIGIN, RES, 2.0)


def _sampled(risk: np.ndarray, valid: np.ndarray, a: np.ndarray, b: np.ndarray, n: int = 40000):
    t = (np.arange(n) + 0.5) / n
    p = a + t[:, None] * (b - a)
    ij = np.floor((p - np.asarray(ORIGIN)) / RES).astype(int)
    length = float(np.linalg.norm(b - a))
    return length * (1.0 + 2.0 * float(risk[ij[:, 0], ij[:, 1]].mean())), bool(valid[ij[:, 0], ij[:, 1]].all())


def test_segment_cost_and_validity_match_dense_sampling(packed) -> None:
    risk, valid, buf = packed
    address = buf.ctypes.data
    rng = np.random.default_rng(6)
    disagree = 0
    for k in range(400):
        a = np.asarray(ORIGIN) + rng.uniform(0.0, [4.999, 3.999])
        b = np.asarray(ORIGIN) + rng.uniform(0.0, [4.999, 3.999])
        if k % 5 == 0:
            b[1] = a[1]  # axis-parallel segments too
        cost, free = _sampled(risk, valid, a, b)
        assert _segment_kernels.segment_cost_2d(address, *a, *b) == pytest.approx(cost, rel=2e-3, abs=1e-9)
        # a sampled check may miss a corner the exact walk sees, never the other way round
        exact = _segment_kernels.segment_free_2d(address, *a, *b)
        assert not (exact and not free)
        disagree += exact != free
    assert disagree <= 4


def test_a_one_cell_wall_is_caught_whatever_the_angle() -> None:
    risk = np.zeros((40, 40), np.float32)
    valid = np.ones((40, 40), bool)
    valid[20, :] = False
    address = (buf := _segment_kernels.pack(risk, valid, (0.0, 0.0), RES, 1.0)).ctypes.data
    rng = np.random.default_rng(7)
    for _ in range(300):
        a = np.array([rng.uniform(0.0, 1.99), rng.uniform(0.0, 3.99)])
        b = np.array([rng.uniform(2.11, 3.99), rng.uniform(0.0, 3.99)])
        assert not _segment_kernels.segment_free_2d(address, *a, *b)
        assert not _segment_kernels.segment_free_3d(address, a[0], a[1], 0.05, b[0], b[1], 0.05)
    del buf


def test_a_segment_through_a_corner_touches_the_side_cells_for_no_length() -> None:
    # the diagonal between the centres of two valid cells passes the shared corner of two
    # invalid ones: every point lies in the closure of a valid cell, which the dilation covers
    valid = np.ones((4, 4), bool)
    valid[1, 2] = valid[2, 1] = False
    buf = _segment_kernels.pack(np.zeros((4, 4), np.float32), valid, (0.0, 0.0), 1.0, 1.0)
    assert _segment_kernels.segment_free_2d(buf.ctypes.data, 1.5, 1.5, 2.5, 2.5)
    assert not _segment_kernels.segment_free_2d(buf.ctypes.data, 1.5, 1.5, 2.5, 2.6)


@pytest.mark.parametrize("floor", [0.0, 0.3])  # 0.3: every cell risky, the heuristic scaled by 1 + w 0.3
def test_grid_search_cost_is_the_shortest_path_of_the_cell_graph(floor: float) -> None:
    rng = np.random.default_rng(8)
    n = 30
    risk = (floor + rng.random((n, n)) * 0.25).astype(np.float32)
    risk[rng.random((n, n)) < 0.25] = 1.0
    risk[0, 0] = risk[-1, -1] = floor
    field = RiskField(risk, RES, (0.0, 0.0))
    grid = PackedGrid(field, 0.0, 0.6, True, 1.5)
    found = grid_path(grid, (0.05, 0.05), ((n - 0.5) * RES, (n - 0.5) * RES))
    # the same graph built independently: 8 neighbours, |ab| (1 + w (ra + rb) / 2)
    valid = (risk <= 0.6).ravel()
    r = risk.astype(np.float64).ravel()
    rows, cols, weights = [], [], []
    index = np.arange(n * n).reshape(n, n)
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        j0, j1 = max(0, -dj), n - max(0, dj)
        a = index[0 : n - di, j0:j1].ravel()
        b = index[di:n, j0 + dj : j1 + dj].ravel()
        ok = valid[a] & valid[b]
        w = RES * math.hypot(di, dj) * (1.0 + 1.5 * 0.5 * (r[a] + r[b]))
        rows.append(a[ok])
        cols.append(b[ok])
        weights.append(w[ok])
    graph = sparse.coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n * n,) * 2)
    dist = csgraph.dijkstra(graph.tocsr(), directed=False, indices=0)
    assert found.reached
    assert found.graph_cost == pytest.approx(dist[n * n - 1], rel=1e-9)


def test_grid_search_stops_after_its_expansion_budget() -> None:
    field = RiskField(np.zeros((40, 40), np.float32), RES, (0.0, 0.0))
    grid = PackedGrid(field, 0.0, 0.6, True, 1.0)
    start, goal = (0.05, 0.05), (3.95, 3.95)  # 39 diagonal steps apart: 40 expansions on open floor
    assert not grid_path(grid, start, goal, max_expansions=39).reached
    found = grid_path(grid, start, goal, max_expansions=40)
    assert found.reached and found.graph_cost == pytest.approx(39 * math.sqrt(2) * RES)


def test_grid_search_reports_an_unreachable_goal() -> None:
    risk = np.zeros((20, 20), np.float32)
    risk[10, :] = 1.0
    field = RiskField(risk, RES, (0.0, 0.0))
    grid = PackedGrid(field, 0.0, 0.6, True, 1.0)
    found = grid_path(grid, (0.25, 1.0), (1.75, 1.0))
    assert not found.reached
    assert found.positions[-1][0] == pytest.approx(0.95)  # the reachable cell nearest the goal


def test_shortcut_never_cuts_closer_to_risk_than_the_path_it_replaces() -> None:
    # a path bent 0.5 m round a contested cell (risk 0.5): the straight cut would be 0.062 m
    # shorter and pay only 0.025 m of risk, so a rule on cost alone takes it; the peak rule
    # keeps the bend, and on an empty map the same bend is pulled straight
    res = 0.05
    risk = np.zeros((200, 60), np.float32)
    risk[100, 20] = 0.5
    bent = np.array([[1.025, 1.025], [5.025, 1.525], [9.025, 1.025]])
    for values, kept in ((risk, [0, 1, 2]), (np.zeros_like(risk), [0, 2])):
        grid = PackedGrid(RiskField(values, res, (0.0, 0.0)), 0.0, 0.6, True, 1.0)
        assert grid.shortcut(bent).tolist() == kept
    grid = PackedGrid(RiskField(risk, res, (0.0, 0.0)), 0.0, 0.6, True, 1.0)
    assert grid.cost(bent[[0, 2]]) < grid.cost(bent)  # the cut would have been cheaper


def test_dubins_kernel_follows_ompl_curves() -> None:
    rho = 0.5
    buf = _segment_kernels.pack(np.zeros((100, 100), np.float32), np.ones((100, 100), bool), (0.0, 0.0), RES, 1.0, rho)
    space = ob.DubinsStateSpace(turningRadius=rho)
    bounds = ob.RealVectorBounds(2)
    bounds.setLow(0.0)
    bounds.setHigh(10.0)
    space.setBounds(bounds)
    si = ob.SpaceInformation(space)
    si.setStateValidityChecker(lambda s: True)
    si.setup()
    a, b, tmp = si.allocState(), si.allocState(), si.allocState()
    rng = np.random.default_rng(9)
    for _ in range(300):
        x1, y1, x2, y2 = rng.uniform(2.0, 8.0, 4)
        t1, t2 = rng.uniform(-math.pi, math.pi, 2)
        a.setXY(x1, y1)
        a.setYaw(t1)
        b.setXY(x2, y2)
        b.setYaw(t2)
        assert _dubins_kernels.dubins_length(buf.ctypes.data, x1, y1, t1, x2, y2, t2) == pytest.approx(space.distance(a, b))
        word, t, p, q = _dubins_kernels._dubins_between(x1, y1, t1, x2, y2, t2, rho)
        for f in (0.3, 0.7, 1.0):
            space.interpolate(a, b, f, tmp)
            x, y, _ = _dubins_kernels.dubins_point(x1, y1, t1, rho, word, t, p, q, (t + p + q) * f)
            assert math.hypot(x - tmp.getX(), y - tmp.getY()) < 1e-9
