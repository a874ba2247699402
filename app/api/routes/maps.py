"""Map resources: create, list, read, delete."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.formats import etags
from app.api.deps import MapNamePath, ServiceDep
from app.schemas import MapCreate, MapInfo

router = APIRouter(prefix="/maps", tags=["maps"])

_NOT_FOUND = {404: {"description": "no map of that name"}}


@router.post("", status_code=201, responses={409: {"description": "the name is taken"},
                                               507: {"description": "no room: FUZZYRISK_MAX_MAPS or FUZZYRISK_MAX_TOTAL_CELLS"}})
async def create_map(body: MapCreate, service: ServiceDep) -> MapInfo:
    """Create an empty map (every cell unknown, risk 0.5)."""
    return await service.maps.create_map(body)


@router.get("")
async def list_maps(service: ServiceDep) -> list[MapInfo]:
    """Every map, by name."""
    return await service.maps.list_maps()


@router.get("/{name}", responses=_NOT_FOUND)
async def get_map(name: MapNamePath, service: ServiceDep, response: Response) -> MapInfo:
    """One map, with ``scans_fused`` and ``version`` (also in the ``X-Map-Version`` header)."""
    info = await service.reads.map_info(name)
    response.headers[etags.VERSION_HEADER] = str(info.version)
    return info


@router.delete("/{name}", status_code=204, response_class=Response, responses=_NOT_FOUND)
async def delete_map(name: MapNamePath, service: ServiceDep) -> Response:
    """Delete a map and everything stored about it (after a batch in flight finishes)."""
    await service.maps.delete_map(name)
    return Response(status_code=204)
