"""Plans on a map's risk, and paths checked under a plan's rules."""

from __future__ import annotations

from fastapi import APIRouter, Response

from planning import STATE_SPACE_NAMES, available_planners
from planning.planners import PLANNERS

from app.formats import etags
from app.api.deps import MapNamePath, ServiceDep
from app.schemas import PathCheckRequest, PathCheckResult, PlannerInfo, Planners, PlanRequest, PlanResult

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


@router.post(
    "/maps/{name}/paths/check",
    responses={
        404: {"description": "no map of that name"},
        413: {"description": "more points than FUZZYRISK_MAX_PATH_POINTS, or segments crossing more than "
                             "10,000,000 cells in all"},
        422: {"description": "invalid parameters: NaN, a point of the wrong size for the state space, a frame_id "
                             "that is not the map's, both or neither of path and poses"},
    },
)
async def check_path(name: MapNamePath, body: PathCheckRequest, service: ServiceDep,
                     response: Response) -> PathCheckResult:
    """Whether a path still holds on the map's current risk (Nav2's IsPathValid), under the rules a plan with the same
    ``robot_radius``, ``max_risk``, ``allow_unknown`` and ``state_space`` is held to, and its cost as a plan computes
    it.

    The points are joined by straight segments and every cell each crosses is checked, as the planner checks every
    path it returns: a path a plan just returned is valid on the same version. A point off the map makes its segment
    invalid. Runs where reads run, not in the planner workers.
    """
    result = await service.path_checks.check(name, body)
    response.headers[etags.VERSION_HEADER] = str(result.version)
    return result
