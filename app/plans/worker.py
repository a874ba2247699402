"""What runs inside a planner worker process: the planner stack warmed up, a plan on a grid, the fields kept.

A plan on a published grid (``app.maps.shared_grids``) gets only the grid's files with its parameters
(``run_shared_plan``), and the worker keeps the ``RiskField`` of each grid it planned on (with the
dilations computed for it) for the next plans on that map version; otherwise the arrays come with
the plan (``run_plan``). Everything here takes and returns plain data: it crosses a process boundary.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from app.ops import process_setup
from app.maps.shared_grids import FieldCache, GridRef
from planning.parameters import DEFAULT_ALLOW_UNKNOWN, DEFAULT_ROBOT_RADIUS

#: How much nicer than the server the planner workers run: a plan (seconds of CPU) takes what scans and reads
#: leave (at the same priority, a 30 s plan, and ten clients' plans on both cores, made an innocent client's map
#: reads 2.6x slower)
PLAN_NICE = 5
#: Bytes of fields a worker keeps when its pool is not told (``PlanPool(field_cache_bytes=...)``).
DEFAULT_FIELD_CACHE_BYTES = 256 * 2**20
#: In a worker: the fields of the published grids it planned on (``run_shared_plan``).
_FIELDS = FieldCache(DEFAULT_FIELD_CACHE_BYTES)


def init_worker(native: bool, field_cache_bytes: int = DEFAULT_FIELD_CACHE_BYTES) -> None:
    """In each new worker: end with the server, use the compiled planner callbacks (``planning/native.py``)
    or not, and compile or load every kernel now, so that no plan waits for it."""
    global _FIELDS
    process_setup.start_worker_process(PLAN_NICE)
    _FIELDS = FieldCache(field_cache_bytes)
    import planning
    from planning import native as compiled

    # OMPL's plain-text warnings would break the service's one-JSON-object-a-line logs; what they
    # warn about comes back in each result (status, message) or is documented (planning/README.md)
    planning.quiet_ompl()
    compiled.set_enabled(native)
    planning.warm_up()  # its plans load (or compile) the compiled callbacks too


def worker_pid() -> int:
    """A task that starts a worker (its initializer warms the planner stack up); the worker's pid."""
    return os.getpid()


def run_plan(
    risk: np.ndarray, observed: np.ndarray, resolution: float, origin: tuple[float, ...], params: dict[str, Any]
) -> dict[str, Any]:
    """Plan on a risk grid (in a worker process); returns ``{"result": ...}`` or ``{"error": ...}``.

    ``params`` are ``planning.plan``'s keyword arguments. A start or goal the planner
    cannot use comes back as ``{"error": {"code": <Nav2 name>, "message": ...}}``, any
    other refusal of the parameters as ``{"invalid": message}``.
    """
    from planning import RiskField

    try:
        field = RiskField(risk, resolution, origin, observed=observed)
    except ValueError as exc:
        return {"invalid": str(exc)}
    return _plan_on(field, params)


def run_shared_plan(ref: GridRef, params: dict[str, Any]) -> dict[str, Any]:
    """``run_plan`` on a published grid: the field this worker kept for it, or one read from its files.

    The field keeps its dilations for the next plan on the same grid (``app.maps.shared_grids.FieldCache``).
    """
    field = _FIELDS.field(ref)
    try:
        return _plan_on(field, params)
    finally:
        _FIELDS.used(ref, params.get("robot_radius", DEFAULT_ROBOT_RADIUS),
                     params.get("allow_unknown", DEFAULT_ALLOW_UNKNOWN))


def worker_fields() -> dict[str, Any]:
    """What this worker keeps (for tests): the grids' risk files, their bytes, and how many fields it read."""
    return {"paths": _FIELDS.paths, "bytes": _FIELDS.nbytes, "loads": _FIELDS.loads, "max_bytes": _FIELDS.max_bytes,
            "pid": os.getpid()}


def _plan_on(field: Any, params: dict[str, Any]) -> dict[str, Any]:
    from planning import PlanError, plan

    try:
        result = plan(field, **params)
    except PlanError as exc:
        return {"error": {"code": str(exc.code), "message": str(exc)}}
    except ValueError as exc:
        return {"invalid": str(exc)}
    return {"result": result.to_json()}
