"""The service's own state: liveness (``Health``) and readiness (``Readiness``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    """Whether the service is ready for traffic (``GET /ready``: 200 when ``status`` is ready, else 503)."""

    status: Literal["ready", "starting", "failed"] = Field(
        description="ready: maps loaded, kernels compiled, planner workers up; starting: not yet; failed: see detail"
    )
    maps_loaded: int = Field(description="maps held (all stored maps are loaded before the service answers at all)")
    maps_quarantined: list[str] = Field(
        default_factory=list,
        description="stored maps set aside at start because their rows are damaged (a checksum fails, a batch "
        "cannot be decoded): each answers 503 with the reason until dropped (DELETE) or the database is restored",
    )
    kernels_compiled: bool = Field(description="the fusion kernels are compiled, or loaded from numba's cache")
    planner_workers_ready: int = Field(description="planner workers started and warmed up")
    planner_workers_wanted: int = Field(
        description="planner workers readiness waits for: FUZZYRISK_PLAN_WORKERS, or 0 when FUZZYRISK_PLAN_WARMUP "
        "is false (they start at the first plan)"
    )
    batches_in_line: int = Field(
        0, description="scan batches accepted or still arriving and not yet applied, over all maps held (each map "
        "holds at most FUZZYRISK_MAX_PENDING_BATCHES): a backlog that grows means fusion does not keep up"
    )
    longest_fusion_job_s: float = Field(
        0.0, description="how long the oldest job in a fusion thread (a batch's fusion, a snapshot, a map's load) "
        "has run so far, in seconds; 0 when they are idle"
    )
    detail: str = Field("", description="what failed, when status is failed")
