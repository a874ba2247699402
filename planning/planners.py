"""The planners ``plan`` can run, by name.

A dict, never an if/elif chain: an unknown name raises ``ValueError`` listing the names
that work, and a name known not to work in the OMPL 2.0.1 wheel says why.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ompl import base as ob
from ompl import geometric as og

GRID = "grid"
#: The state spaces ``plan`` accepts, by name (``spaces.STATE_SPACES`` holds one entry per name, in this
#: order): named here, where importing compiles nothing, for processes that only list them.
STATE_SPACE_NAMES = ("R2", "SE2", "Dubins", "ReedsShepp", "R3")


@dataclass(frozen=True)
class PlannerSpec:
    """How to make and drive one planner.

    Attributes
    ----------
    name : str
        The registry key (OMPL's class name, or "grid").
    optimizing : bool
        Anytime optimizer that uses the whole time limit; otherwise the solve stops at
        the first solution.
    make : callable or None
        ``make(si) -> planner``, configured; None for the grid planner.
    rate : float
        Termination checks per second a seeded plan budgets for (``plan`` runs
        ``SEEDED_BUDGET_SHARE * seconds * rate`` of them, so that the count, not the clock,
        ends it and the plan is reproducible). For the anytime planners, the slowest rate
        measured on the benchmark maps with the compiled callbacks (``native.py``) on the
        reference machine (2 vCPU EPYC; RRTstar 50-60 k/s, InformedRRTstar and SORRTstar
        40-48 k/s, BITstar 126-220 k/s), so a seeded plan takes up to about 60 % of its
        time there and leaves the rest as margin for a slower machine. The others stop at
        their first solution, usually long before their budget.
    """

    name: str
    optimizing: bool
    make: Callable[[ob.SpaceInformation], ob.Planner] | None
    rate: float


def _rrtstar(si: ob.SpaceInformation) -> ob.Planner:
    planner = og.RRTstar(si)
    # r-disc neighbourhoods: far fewer objective calls per iteration than OMPL's k-nearest
    # default (k = 36 log n in the plane), each one a walk over the cells of an edge
    planner.setKNearest(False)
    return planner


def _informed_rrtstar(si: ob.SpaceInformation) -> ob.Planner:
    planner = og.InformedRRTstar(si)
    planner.setKNearest(False)
    return planner


def _sorrtstar(si: ob.SpaceInformation) -> ob.Planner:
    planner = og.SORRTstar(si)
    planner.setKNearest(False)
    return planner


PLANNERS: dict[str, PlannerSpec] = {
    spec.name: spec
    for spec in (
        PlannerSpec(GRID, optimizing=True, make=None, rate=0.0),
        PlannerSpec("RRTConnect", optimizing=False, make=og.RRTConnect, rate=50000.0),
        PlannerSpec("RRT", optimizing=False, make=og.RRT, rate=50000.0),
        PlannerSpec("RRTstar", optimizing=True, make=_rrtstar, rate=50000.0),
        PlannerSpec("InformedRRTstar", optimizing=True, make=_informed_rrtstar, rate=40000.0),
        PlannerSpec("SORRTstar", optimizing=True, make=_sorrtstar, rate=40000.0),
        PlannerSpec("BITstar", optimizing=True, make=og.BITstar, rate=120000.0),
        PlannerSpec("KPIECE1", optimizing=False, make=og.KPIECE1, rate=50000.0),
        PlannerSpec("BKPIECE1", optimizing=False, make=og.BKPIECE1, rate=50000.0),
        PlannerSpec("LBKPIECE1", optimizing=False, make=og.LBKPIECE1, rate=50000.0),
    )
}

_PRM_WHY = (
    "its roadmap grows in a second thread that calls the Python validity checks while solve() holds "
    "the GIL: deadlocks with a Python objective or termination condition (OMPL 2.0.1 wheel), and hung "
    "even with OMPL's own objective and timer in our Dubins tests"
)
UNSUPPORTED: dict[str, str] = {
    "PRM": _PRM_WHY,
    "PRMstar": _PRM_WHY,
    "LazyPRM": _PRM_WHY,
    "AORRTC": "ignores a Python optimization objective in the OMPL 2.0.1 wheel",
    "FMT": "not anytime: overruns its time limit (7x with Dubins) and fails in R3 at 1000 samples",
    "BFMT": "not anytime: overruns its time limit (6x with Reeds-Shepp) at 1000 samples",
    "AITstar": "not in the OMPL 2.0.1 wheel",
    "LazyPRMstar": "not in the OMPL 2.0.1 wheel",
    "SST": "not in the OMPL 2.0.1 wheel (geometric)",
}


def available_planners() -> tuple[str, ...]:
    """Names ``plan`` accepts, in registry order ("grid" first)."""
    return tuple(PLANNERS)


def planner_spec(name: str) -> PlannerSpec:
    """The spec registered under ``name``.

    Raises
    ------
    ValueError
        Naming ``planner``: an unknown name, or one known not to work (with the reason);
        the message lists the names that work.
    """
    try:
        return PLANNERS[name]
    except (KeyError, TypeError):
        pass
    choices = ", ".join(available_planners())
    reason = UNSUPPORTED.get(name) if isinstance(name, str) else None
    if reason is not None:
        raise ValueError(f"planner: {name!r} is not supported: {reason}; choose one of: {choices}")
    raise ValueError(f"planner: unknown planner {name!r}; choose one of: {choices}")
