"""The Foxglove live view's messages and bounds (app/foxglove_live.py), without a server.

The view as a client sees it, frames included, is tested in ``tests/e2e/test_foxglove.py``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the foxglove extra (foxglove-sdk) is not installed")

from app.reads import foxglove as live
from app.config import Settings
from app.ops.process_setup import StartupError, foxglove_sdk_missing
from app.maps import GridSnapshot
from fuzzyocc.config import GridSpec


def snapshot(risk: np.ndarray, observed: np.ndarray, resolution: float = 0.05) -> GridSnapshot:
    nx, ny = risk.shape
    spec = GridSpec(origin=(-1.0, 2.0), size=(nx * resolution, ny * resolution), resolution=resolution)
    assert spec.shape == risk.shape
    return GridSnapshot(spec, 1, risk.astype(np.float32), observed, "robot1/map")


@pytest.mark.parametrize(("shape", "cap", "k"), [((100, 100), 10_000, 1), ((100, 100), 9_999, 2),
                                                 ((2000, 2000), 1_000_000, 2), ((4000, 4000), 1_000_000, 4),
                                                 ((3001, 7), 1_000, 7), ((1, 5000), 1_000, 5)])
def test_the_block_factor_is_the_smallest_that_fits(shape: tuple[int, int], cap: int, k: int) -> None:
    assert live.block_factor(shape, cap) == k
    nx, ny = shape
    assert math.ceil(nx / k) * math.ceil(ny / k) <= cap
    assert k == 1 or math.ceil(nx / (k - 1)) * math.ceil(ny / (k - 1)) > cap


def test_a_block_is_the_largest_risk_of_its_observed_cells() -> None:
    risk = np.full((5, 3), 0.5, dtype=np.float32)  # 0.5: unknown, the risk of a cell never observed
    observed = np.zeros((5, 3), dtype=bool)
    risk[0, 0], observed[0, 0] = 0.1, True  # free, beside unknown cells: the block is free, not 0.5
    risk[2:4, 0:2], observed[2:4, 0:2] = 0.2, True
    risk[3, 1] = 0.97  # one obstacle among free cells: it stays
    risk[4, 2], observed[4, 2] = 0.8, True  # in a partial block at the far corner
    blocks, seen = live.max_blocks(risk, observed, 2)
    assert blocks.dtype == np.float32 and blocks.shape == seen.shape == (3, 2)
    assert blocks.tolist() == [[pytest.approx(0.1), 0.5], [pytest.approx(0.97), 0.5], [0.5, pytest.approx(0.8)]]
    assert seen.tolist() == [[True, False], [True, False], [False, True]]
    assert live.max_blocks(risk, observed, 1)[0] is risk  # no blocks: the map itself, not a copy


def test_a_grid_over_the_cap_goes_in_blocks_at_a_coarser_resolution() -> None:
    rng = np.random.default_rng(3)
    risk = rng.uniform(0.0, 1.0, (300, 200)).astype(np.float32)
    observed = rng.uniform(size=(300, 200)) < 0.9
    message = live.grid_message(snapshot(risk, observed), "robot1/map", max_cells=10_000)  # 60,000 cells: k = 3
    encoded = message.encode()
    assert 100 * 67 * live.GRID_CELL.itemsize < len(encoded) < 100 * 67 * live.GRID_CELL.itemsize + 512
    whole = live.grid_message(snapshot(risk, observed), "robot1/map")  # no cap: every cell
    assert len(whole.encode()) > 300 * 200 * live.GRID_CELL.itemsize
    assert b"robot1/map" in encoded


def test_a_slow_clients_backlog_is_bounded_in_bytes() -> None:
    """The SDK bounds a client's queue in messages: as many as fit the byte budget at the largest message."""
    default = Settings().foxglove_max_cells
    assert default == 1_000_000 and live.client_backlog(default) == 8  # 8 grids of 8 MB: 64 MiB
    for cap in (10_000, default, 4_000_000):  # FUZZYRISK_FOXGLOVE_MAX_CELLS: its least, default and most
        backlog = live.client_backlog(cap)
        largest = max(cap * live.GRID_CELL.itemsize, live.MAX_CLOUD_POINTS * 12)
        assert live.MIN_CLIENT_BACKLOG <= backlog <= live.MAX_CLIENT_BACKLOG
        assert backlog * largest <= max(live.CLIENT_BACKLOG_BYTES, live.MIN_CLIENT_BACKLOG * largest)
    assert live.client_backlog(4_000_000) * 4_000_000 * live.GRID_CELL.itemsize <= 128 * 10**6  # at the largest cap
    with pytest.raises(ValueError, match="foxglove_max_cells"):
        Settings(foxglove_max_cells=4_000_001)


def test_the_missing_sdk_is_said_in_the_words_of_the_start_check() -> None:
    error: Any = foxglove_sdk_missing(ImportError("No module named 'foxglove'"))
    assert isinstance(error, StartupError)
    assert str(error).startswith("FUZZYRISK_FOXGLOVE_PORT needs the Foxglove SDK (No module named 'foxglove')")
    install = "pip install 'fuzzyrisk[foxglove]' (an image: docker build --build-arg EXTRAS=foxglove)"
    assert str(error).endswith(f"{install}, or unset FUZZYRISK_FOXGLOVE_PORT")
