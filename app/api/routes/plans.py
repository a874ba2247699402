"""Plans on a map's risk."""

from __future__ import annotations

from fastapi import APIRouter, Response

from planning import STATE_SPACE_NAMES, available_planners
from planning.planners import PLANNERS

from app.formats import etags
from app.api.deps import MapNamePath, ServiceDep
from app.schemas import PlannerInfo, Planners, PlanRequest, PlanResult

router = APIRouter(tags=["plans"])


@router.get("/planners")
async def planners() -> Planners:
    """The planner names and state spaces a plan request accepts (what works in this build)."""
    return Planners(
        planners=[PlannerInfo(name=n, optimizing=PLANNERS[n].optimizing) for n in available_planners()],
        state_spaces=list(STATE_SPACE_NAMES),
    )


@router.post(
    "/maps/{name}/plan",
    responses={
        404: {"description": "no map of that name"},
        422: {
            "description": "invalid parameters (code INVALID or VALIDATION_ERROR); a start or goal that "
            "cannot be used answers Nav2's name for why as the code: START_OUTSIDE_MAP, GOAL_OUTSIDE_MAP, "
            "START_OCCUPIED or GOAL_OCCUPIED"
        },
        503: {"description": "every planner worker is busy; retry (Retry-After)"},
    },
)
async def plan(name: MapNamePath, body: PlanRequest, service: ServiceDep, response: Response) -> PlanResult:
    """A path from ``start`` to ``goal`` whose observed cells under the robot stay at or below ``max_risk``
    (default 0.45: cells with net free evidence); never-observed cells are allowed unless ``allow_unknown``
    is false, whatever ``max_risk`` says.

    Cost = length + ``risk_weight`` * integral of risk along the path (never-observed cells count 0.5).
    Runs in a worker process.
    """
    result = await service.plans.plan(name, body)
    response.headers[etags.VERSION_HEADER] = str(result.version)
    return result
