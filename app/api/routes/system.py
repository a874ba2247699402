"""Liveness, readiness and metrics: open even when an API key is configured (probes and scrapers carry none)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from app.api.deps import ServiceDep
from app.schemas import Health, Readiness

router = APIRouter(tags=["operations"])


@router.get("/health", response_model=Health)
async def health() -> Health:
    """Answers at once, also while plans and fusions run (they never run on the event loop)."""
    return Health(status="ok")


# HEAD too, for load balancers and `curl -I` (a route of its own: one method per OpenAPI operation id)
@router.head("/health", include_in_schema=False)
async def health_head() -> Response:
    return Response(status_code=200)


@router.get("/ready", response_model=Readiness, responses={503: {"model": Readiness, "description": "not ready yet"}})
async def ready(service: ServiceDep, response: Response) -> Readiness:
    """200 once the maps are loaded, the fusion kernels compiled and the planner workers up; 503 until then
    (``Retry-After``). What a container's health check, a load balancer or a robot's start-up should wait for."""
    readiness = service.readiness()
    if readiness.status != "ready":
        response.status_code = 503
        response.headers["Retry-After"] = "1"
    return readiness


@router.head("/ready", include_in_schema=False)
async def ready_head(service: ServiceDep) -> Response:
    ready_now = service.readiness().status == "ready"
    return Response(status_code=200 if ready_now else 503, headers={} if ready_now else {"Retry-After": "1"})


@router.get("/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
async def metrics(request: Request) -> Response:
    """Prometheus text format: requests, fusion, plans, snapshots."""
    return Response(generate_latest(request.app.state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
