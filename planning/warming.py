"""Compiling, or loading from numba's on-disk cache, the kernels a state space's plans run: once per space and process."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable

import numpy as np

from planning.field import RiskField
from planning.planners import GRID
from planning.spaces import STATE_SPACES, SpaceSpec

log = logging.getLogger(__name__)

_WARM_LOCK = threading.RLock()  # re-entered by the warm-up plans' own calls of plan()
_warmed: set[str] = set()  # state spaces whose kernels this process has compiled or loaded
_warming: set[str] = set()  # being warmed up (by the thread holding _WARM_LOCK)


def is_warm(state_space: str) -> bool:
    """Whether this process has compiled or loaded the kernels of ``state_space`` (no lock taken)."""
    return state_space in _warmed


def warm_up(state_spaces: str | Iterable[str] = tuple(STATE_SPACES)) -> float:
    """Compile, or load from numba's on-disk cache, the kernels that plans in these spaces run.

    Plans a small problem (a wall, a risk gradient, an unobserved patch: the compiled
    callbacks' self-check in ``native.py`` runs on it) once per space and process, with the
    grid planner too in R2 and R3; later calls for a space return at once. ``plan`` calls it for
    its own space before its clock starts; a service calls it at startup so that no request
    waits for it. A failed warm-up plan is logged, never raised: the real plan then reports
    what is wrong. Returns the seconds taken.
    """
    started = time.perf_counter()
    names = (state_spaces,) if isinstance(state_spaces, str) else tuple(state_spaces)
    with _WARM_LOCK:  # a second thread waits here until the kernels are ready
        for name in names:
            sspec = STATE_SPACES.get(name)
            if sspec is None:
                raise ValueError(f"state_space: unknown {name!r}; choose one of: {', '.join(STATE_SPACES)}")
            if name in _warmed or name in _warming:
                continue  # done, or being done by this very thread (the warm-up plans call plan())
            _warming.add(name)
            try:
                _warm_space(sspec)
            finally:
                _warming.discard(name)
            _warmed.add(name)
    return time.perf_counter() - started


def _warm_space(sspec: SpaceSpec) -> None:
    from planning.query import plan  # which calls warm_up: imported when first needed

    rng = np.random.default_rng(0)
    shape = (30, 30) if sspec.field_ndim == 2 else (30, 30, 8)
    risk = rng.uniform(0.0, 0.4, shape).astype(np.float32)
    risk[15, :20] = 1.0  # a wall across x = 1.5 m, open at y >= 2 m
    observed = np.ones(shape, bool)
    observed[24:, 24:] = False
    field = RiskField(risk, 0.1, (0.0,) * len(shape), observed=observed)
    z = [0.4] if sspec.field_ndim == 3 else [0.0]
    start, goal = [0.5, 0.5, *z][: sspec.state_dim], [2.5, 0.5, *z][: sspec.state_dim]
    planners = [GRID, "RRTConnect"] if sspec.name in ("R2", "R3") else ["RRTConnect"]
    for planner in planners:
        for allow_unknown in (True, False):
            try:
                # unseeded: OMPL's seed is process-wide, and a warm-up must not fix the RNG of the
                # process's later unseeded plans
                plan(field, start, goal, planner=planner, state_space=sspec.name, time_limit=10.0,
                     robot_radius=0.1, allow_unknown=allow_unknown,
                     turning_radius=0.3 if sspec.curved else None)
            except Exception:  # noqa: BLE001 - reported by the real plan, not here
                log.warning("warm-up plan in %s with %s failed", sspec.name, planner, exc_info=True)
