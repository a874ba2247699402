"""A map's trajectory: out, the sensor poses of its stored scans with their stamps (a ``nav_msgs/Path``); in, a
corrected one the map is rebuilt at, and that rebuild's status."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response

from app.api.deps import MapNamePath, ServiceDep
from app.api.largebody import bytes_response
from app.formats import etags
from app.maps.correction import SensorOffset
from app.schemas import RebuildAccepted, RebuildStatus, Trajectory

router = APIRouter(prefix="/maps", tags=["trajectory"])


@router.get(
    "/{name}/trajectory",
    response_class=Response,
    responses={
        200: {"model": Trajectory, "description": "the trajectory (a nav_msgs/Path with the map's counts)",
              "headers": {etags.VERSION_HEADER: {"description": "the map version of the answer",
                                                 "schema": {"type": "integer"}}}},
        404: {"description": "no map of that name"},
        413: {"description": "more stored scans than FUZZYRISK_MAX_TRAJECTORY_POSES"},
    },
)
async def get_trajectory(name: MapNamePath, service: ServiceDep) -> Response:
    """The sensor pose of every stored scan of the map, in the order fused, with the scan's stamp: a ``nav_msgs/Path``
    (``header``, ``poses``) as a plan answers one.

    A scan's stamp is its JSON ``header.stamp``, its ROS message's (CDR body, bag), or, for a scan posted without
    one, the time the service received its batch. Scans stored before stamps were kept are stamped 0 and counted
    in ``unstamped``. The scans are those of the map's history: every batch after its base snapshot (``from_version``;
    the oldest leave it for the base beyond ``FUZZYRISK_MAX_HISTORY_BYTES``).
    """
    data, version = await service.reads.trajectory(name)
    return bytes_response(data, media_type="application/json", headers={etags.VERSION_HEADER: str(version)})


def _offset(
    offset_x: Annotated[float, Query(allow_inf_nan=False)] = 0.0,
    offset_y: Annotated[float, Query(allow_inf_nan=False)] = 0.0,
    offset_z: Annotated[float, Query(allow_inf_nan=False)] = 0.0,
    offset_qx: Annotated[float, Query(allow_inf_nan=False)] = 0.0,
    offset_qy: Annotated[float, Query(allow_inf_nan=False)] = 0.0,
    offset_qz: Annotated[float, Query(allow_inf_nan=False)] = 0.0,
    offset_qw: Annotated[float, Query(allow_inf_nan=False)] = 1.0,
) -> SensorOffset | None:
    """The sensor's fixed pose on the robot whose path is given (a static TF ``base_link -> laser``); None when the
    path's poses are the sensor's (no offset given, or the identity)."""
    position, quaternion = (offset_x, offset_y, offset_z), (offset_qx, offset_qy, offset_qz, offset_qw)
    return None if position == (0.0, 0.0, 0.0) and quaternion == (0.0, 0.0, 0.0, 1.0) else (position, quaternion)


@router.put(
    "/{name}/trajectory",
    status_code=202,
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/CorrectedPath"}}}}},
    responses={
        404: {"description": "no map of that name"},
        409: {"description": "no stored scan has a stamp in the path's range, or a point cloud does"},
        413: {"description": "more poses than FUZZYRISK_MAX_TRAJECTORY_POSES"},
        422: {"description": "another frame than the map's, stamps not strictly increasing, a quaternion that is "
                             "not a unit one, a pose in range that tilts the scanner off level"},
    },
)
async def put_trajectory(name: MapNamePath, request: Request, service: ServiceDep,
                         offset: Annotated[SensorOffset | None, Depends(_offset)]) -> RebuildAccepted:
    """Correct the map's past poses (a SLAM node's corrected ``nav_msgs/Path`` after a loop closure): every stored scan
    whose stamp lies in the path's ``[first, last]`` stamp takes the pose there (translation linear, rotation slerp,
    as tf2 interpolates; a scan stamped as a pose takes exactly that pose); the others, and scans stored after this
    request, keep theirs. The poses are the sensor's, unless the ``offset_*`` query gives the sensor's fixed pose on
    the robot (a static TF ``base_link -> laser``): then each is the path's pose composed with it.

    The correction is durable before the answer (``202``); the map is then rebuilt from its stored history in the
    background (``GET /maps/{name}/rebuild`` follows it) and replaces the current map when complete (its version + 1);
    until then reads and plans are served from the current map. A new PUT supersedes a rebuild under way.
    """
    # the body as a CorrectedPath (its schema below), validated in a parse thread, or the parse process when large
    return RebuildAccepted(rebuild=await service.refusions.correct(name, await request.body(), offset))


@router.get("/{name}/rebuild", responses={404: {"description": "no map of that name"}})
async def get_rebuild(name: MapNamePath, service: ServiceDep) -> RebuildStatus:
    """The map's latest rebuild at a corrected trajectory: ``running`` (scans done of the total, time elapsed, an
    estimate of the time left), ``done`` (the version the rebuilt map became), ``failed`` (with why), or ``none``."""
    return await service.refusions.status(name)
