"""Plans on a map's risk: checked here, solved in the planner worker processes on the map's published grid."""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Awaitable, Callable

from app.ros import messages_out
from app.ros import msgtypes
from app.config import Settings
from app.errors import Invalid, PlanRejected, TooLarge
from app.maps import GridSnapshot, Lease, MapEntry, PlanGrids, copy_limit, is_current
from app.ops.metrics import Metrics
from app.plans.pool import PlanPool
from app.plans.worker import run_plan, run_shared_plan
from app.reads.service import MapReads
from app.schemas import PlanRequest, PlanResult
from fuzzyocc.maps import Window
from planning.budget import wall_clock_limit
from planning.planners import planner_spec

#: Grace added to a plan's time limit before its worker is presumed stuck: setup, dilation, dense check.
PLAN_GRACE_S = 20.0


#: Metres a growing map's plan grid reaches past its bounds, the start and the goal (and the robot's radius): room to
#: go around what the map has seen, through never-observed space where ``allow_unknown`` lets it.
GROWING_PLAN_MARGIN_M = 2.0


class MapPlans:
    """``plan`` requests: the map's grid leased to a worker process, the answer shaped as a ROS path."""

    def __init__(self, settings: Settings, metrics: Metrics, current: Callable[[str], Awaitable[MapEntry]],
                 reads: MapReads, grids: PlanGrids, pool: PlanPool, notify: Callable[..., None]) -> None:
        self.settings = settings
        self.metrics = metrics
        self._current = current  # ``WritePath.current``: the map with every acknowledged batch applied
        self._reads = reads
        self._grids = grids
        self._plans = pool
        self._notify = notify

    async def plan(self, name: str, request: PlanRequest) -> PlanResult:
        """Plan on the map's current risk in a worker process (``planning.plan`` checks the parameters).

        The worker gets the map version's published grid (``app.maps.shared_grids``), written by the first plan
        on that version; or, when it cannot be published, the arrays themselves.
        """
        self._check_plan(request)
        started = time.perf_counter()  # the wait for the grid is part of what the client waits for
        # the path's stamp: when the plan was taken up, as Nav2's planners stamp a path when they start it
        stamp = msgtypes.ros_time_of_ns(time.time_ns())
        entry = await self._current(name)
        # goal_yaw only orients the answer's last pose: the planner never sees it
        params = request.model_dump(exclude_none=True, exclude={"goal_yaw"})
        timeout = wall_clock_limit(request.time_limit, request.seed is not None) + PLAN_GRACE_S
        outcome, source, version = "error", "shared", entry.version
        grid: GridSnapshot | None = None
        lease: Lease | None = None
        window: Window | None = None
        if entry.map.growing:
            # a growing map's plan works on its bounds grown to hold the start, the goal and the robot (beyond the
            # bounds: never observed); the grid published for the version serves the plans that need that window
            window, version = await self._window_around(entry, request)
            lease = self._grids.lease(entry.uid, version)
            if lease is not None and not _covers(lease, window):
                lease.release()
                lease = None
                grid = await self._copy(entry, window)  # another window than the published one: shipped
                source, version = "shipped", grid.version
        else:
            lease = self._grids.lease(entry.uid, version)  # no await since the version was read
        try:
            if lease is None and grid is None:
                async with self._reads.big_read(entry.spec if window is None else window):
                    # a big map's copy takes its turn as big reads do
                    grid = (await self._reads.read_grid_of(entry) if window is None
                            else await self._reads.read_cells(entry, window))
                    source, version = "published", grid.version
                    lease = await self._grids.publish(
                        entry.uid, grid.version, grid.risk, grid.observed, grid.spec.resolution, grid.spec.origin,
                        current=functools.partial(is_current, entry, grid.version),
                    )
                    if lease is not None and window is not None and not _covers(lease, window):
                        lease.release()  # another plan published another window of this version meanwhile
                        lease = None
            self.metrics.plan_grids.labels("shipped" if lease is None else source).inc()
            if lease is not None:
                answer = await self._plans.run(run_shared_plan, timeout, lease.ref, params, key=name)
            else:
                assert grid is not None
                answer = await self._plans.run(
                    run_plan, timeout, grid.risk, grid.observed, grid.spec.resolution, grid.spec.origin, params,
                    key=name,
                )
            if "error" in answer:
                outcome = "rejected"
                raise PlanRejected(answer["error"]["code"], answer["error"]["message"])
            if "invalid" in answer:
                outcome = "invalid"
                raise Invalid(answer["invalid"])
            result = answer["result"]
            outcome = result["status"]
            path_msg = messages_out.path_message(result["path"], state_space=result["state_space"],
                                                 frame_id=entry.frame_id, stamp=stamp, goal_yaw=request.goal_yaw)
            plan = PlanResult(**result, version=version, **path_msg)
            self._notify("plan_made", name, plan, entry.frame_id)
            return plan
        finally:
            if lease is not None:
                lease.release()
            self.metrics.plan_seconds.labels(request.planner, outcome).observe(time.perf_counter() - started)

    async def _window_around(self, entry: MapEntry, request: PlanRequest) -> tuple[Window, int]:
        """A growing map's plan window for ``request`` and the version it is of: its bounds and the start and goal,
        grown by the robot's radius and ``GROWING_PLAN_MARGIN_M``. Where that passes the largest box (a 3-D lidar
        map at 0.1 m), only its part within the start and goal's distance of their box (and the margin)."""
        ndim = entry.spec.ndim
        ends = [request.start[:ndim], request.goal[:ndim]]
        if any(len(p) < ndim for p in ends):
            raise Invalid(f"start and goal need {ndim} coordinates on this {ndim}-D map")
        async with entry.apply_lock:  # the bounds of the version read
            margin = request.robot_radius + GROWING_PLAN_MARGIN_M
            # bounded as the grid of a fixed map's plan is, by the largest box: the same cells plan alike in both
            limit = copy_limit(self.settings)
            try:
                window = entry.map.window_around(ends, margin)
                if window.cells() > limit:
                    # the whole map is past what a plan may copy (the Ouster frames at 0.1 m: 60 x 58 x 14 m): the
                    # part around the two ends, as far again as they are apart, holds the detours a path between
                    # them takes
                    apart = math.dist(ends[0], ends[1])
                    window = entry.map.window_around(ends, margin, reach=margin + apart)
            except ValueError as exc:
                raise Invalid(str(exc)) from None
            if window.cells() > limit:
                raise TooLarge(f"a plan between these points works on {window.cells():,} cells of this growing map, "
                               f"more than a fixed map's largest box ({limit:,}: FUZZYRISK_MAX_MAP_CELLS or 64 M, "
                               "the larger): plan between nearer points")
            return window, entry.version

    async def _copy(self, entry: MapEntry, window: Window) -> GridSnapshot:
        async with self._reads.big_read(window):
            return await self._reads.read_cells(entry, window)

    def _check_plan(self, request: PlanRequest) -> None:
        """What can be refused without a worker: the service's time limit, and an unknown planner."""
        if request.time_limit > self.settings.max_plan_time_s:
            raise Invalid(
                f"time_limit {request.time_limit} s is above the limit of {self.settings.max_plan_time_s} s "
                "(FUZZYRISK_MAX_PLAN_TIME_S)"
            )
        try:
            planner_spec(request.planner)  # lists the planners that work
        except ValueError as exc:
            raise Invalid(str(exc)) from None
        if request.goal_yaw is not None and request.state_space in messages_out.YAW_SPACES:
            raise Invalid(f"goal_yaw is for R2 and R3 paths; in {request.state_space} give the goal's yaw as its "
                          "third value [x, y, theta] and leave goal_yaw out")


def _covers(lease: Lease, window: Window) -> bool:
    """Whether a published grid is exactly ``window`` (a growing map's plans need their own window)."""
    spec = window.spec()
    return lease.ref.origin == tuple(float(v) for v in spec.origin) and lease.ref.shape == tuple(window.shape)
