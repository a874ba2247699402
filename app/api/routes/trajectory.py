"""A map's trajectory: the sensor poses of its stored scans, with their stamps, as a ``nav_msgs/Path``."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.api.deps import MapNamePath, ServiceDep
from app.api.largebody import bytes_response
from app.formats import etags
from app.schemas import Trajectory

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
