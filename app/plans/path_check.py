"""Path checks (``POST /maps/{name}/paths/check``, Nav2's ``IsPathValid``): a path held to a plan's rules on the
map's current grid by the planner's own dense check (``planning.check_path``).

A check runs where reads run (a read thread; a big map's in its turn in the big reads' lane), not in the planner
workers: it walks the cells of one path on the part of the map the path reaches, work that would otherwise wait in
the plans' queue behind seconds of solving.
"""

from __future__ import annotations

import dataclasses
import functools

from app.config import Settings
from app.errors import Invalid, TooLarge
from app.maps import GridSnapshot
from app.reads.service import MapReads
from app.ros.path_in import check_frames, path_points
from app.schemas import PathCheckRequest, PathCheckResult, PathRules
from planning import RiskField


class PathChecks:
    """``check`` requests: the point count bounded, then the check in a read thread on one version of the map."""

    def __init__(self, settings: Settings, reads: MapReads) -> None:
        self.settings = settings
        self._reads = reads

    async def check(self, name: str, request: PathCheckRequest) -> PathCheckResult:
        """Whether ``request``'s path holds on the map's current risk, and its measures, as a plan has them."""
        given = request.path if request.path is not None else request.poses
        assert given is not None  # PathCheckRequest holds one of them
        if len(given) > self.settings.max_path_points:
            raise TooLarge(f"{len(given)} points, more than the limit of {self.settings.max_path_points} "
                           "(FUZZYRISK_MAX_PATH_POINTS): check the path in parts")
        return await self._reads.computed(name, functools.partial(_check_on, request))


def _check_on(request: PathCheckRequest, grid: GridSnapshot) -> PathCheckResult:
    """The check of ``request`` on ``grid`` (in a read thread)."""
    # imported here: the server loads the planner's kernels when a check (or the warm-up) needs them, not as it starts
    from planning.checks import space_spec
    from planning.path_check import PathTooLong, check_path

    field = RiskField(grid.risk, grid.spec.resolution, grid.spec.origin, observed=grid.observed)
    rules = request.model_dump(include=set(PathRules.model_fields))
    try:
        if request.poses is not None:
            check_frames(grid.frame_id, request.header, request.poses)
            path = path_points(request.poses, space_spec(request.state_space, field).name)
        else:
            path = request.path
        checked = check_path(field, path, **rules)
    except PathTooLong as exc:
        raise TooLarge(str(exc)) from None
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    return PathCheckResult(**dataclasses.asdict(checked), version=grid.version)
