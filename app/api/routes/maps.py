"""Map resources: create (empty, or from a saved map), list, read, change, clear a region, delete."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response

from app.formats import etags, saved_maps
from app.api.deps import MapNamePath, ServiceDep
from app.maps.logcodec import Clear, SetForget
from app.schemas import Cleared, ClearRegion, MapChange, MapCreate, MapImport, MapInfo
from app.service import map_import

router = APIRouter(prefix="/maps", tags=["maps"])

_NOT_FOUND = {404: {"description": "no map of that name"}}
_ROOM = {409: {"description": "the name is taken"},
         507: {"description": "no room: FUZZYRISK_MAX_MAPS or FUZZYRISK_MAX_TOTAL_CELLS"}}

_IMPORT_DOC = f"""\
Create a map from a saved map: a fixed 2-D map of the file's resolution, origin and size, whose
cells start from the file (occupied cells as occupied evidence, free as free, unknown as never
observed), each as if `prior_scans` scans had agreed on it; live scans then fuse on top. The import
is the map's first batch (version 1): durable before the answer, replayed at every start.

The body, by its Content-Type:

* `{saved_maps.ZIP}`: a zip of a Nav2 `map.yaml` and the image it names (what `export/nav2` gives, or
  map_saver's two files zipped);
* `{saved_maps.MULTIPART}`: the YAML as part `{saved_maps.YAML_PART}` and the image as part
  `{saved_maps.IMAGE_PART}` (its file name the one the YAML names);
* `{map_import.JSON}`: a `nav_msgs/OccupancyGrid` (`OccupancyGridMessage`: what `GET
  /maps/{{name}}/occupancy_grid` answers, or rosbridge's shape);
* `{map_import.CDR_MEDIA_TYPE}`: one CDR-serialized OccupancyGrid (what `occupancy_grid.cdr` answers).

A Nav2 map is read as map_server's `loadMapFromFile` reads it, in its `mode` (trinary, scale, raw) with
its `occupied_thresh`, `free_thresh` and `negate`; a YAML origin with a yaw other than 0 (or a rotated
OccupancyGrid origin) is refused. In scale mode, and for values between 0 and 100, a cell takes the
evidence of at most `prior_scans` scans whose risk is nearest its occupancy. A file that is not a map,
or does not match its YAML, is refused (422) and nothing is created; so is one over the limits (413:
`FUZZYRISK_MAX_MAP_CELLS` from the image's header, before its pixels are decoded; the body and each zip
entry's declared size by `FUZZYRISK_MAX_BODY_BYTES`).
"""
_BINARY = {"schema": {"type": "string", "format": "binary"}}
_IMPORT_BODY: dict[str, Any] = {"requestBody": {"required": True, "content": {
    saved_maps.ZIP: _BINARY,
    saved_maps.MULTIPART: {"schema": {"type": "object", "required": [saved_maps.YAML_PART, saved_maps.IMAGE_PART],
                                      "properties": {saved_maps.YAML_PART: {"type": "string", "format": "binary"},
                                                     saved_maps.IMAGE_PART: {"type": "string", "format": "binary"}}}},
    map_import.JSON: {"schema": {"$ref": "#/components/schemas/OccupancyGridMessage"}},
    map_import.CDR_MEDIA_TYPE: _BINARY,
}}}


@router.post("", status_code=201, responses=_ROOM)
async def create_map(body: MapCreate, service: ServiceDep) -> MapInfo:
    """Create an empty map (every cell unknown, risk 0.5)."""
    return await service.maps.create_map(body)


@router.post(
    "/import", status_code=201, openapi_extra=_IMPORT_BODY, description=_IMPORT_DOC,
    responses={**_ROOM, 413: {"description": "the body, a zip entry or the map over a limit (the message names it)"},
               415: {"description": "a Content-Type other than a zip, a form, or an OccupancyGrid as JSON or CDR"}},
)
async def import_map(query: Annotated[MapImport, Query()], request: Request, service: ServiceDep) -> MapInfo:
    """Create a map from a saved map: a Nav2 map.yaml + image, or a nav_msgs/OccupancyGrid."""
    return await map_import.import_map(service, query, content_type=request.headers.get("content-type", ""),
                                       body=request.stream())


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


@router.patch("/{name}", responses={**_NOT_FOUND, 422: {"description": "a setting that cannot change, or a bayes "
                                                                       "map's forget_beyond"}})
async def change_map(name: MapNamePath, body: MapChange, service: ServiceDep) -> MapInfo:
    """Change a map's settings that may change (``forget_beyond``), in its place among the map's batches: durable
    before the answer, replayed at every start."""
    if "forget_beyond" in body.model_fields_set:
        await service.writes.add_edit(name, SetForget(body.forget_beyond))
    return await service.reads.map_info(name)


@router.post("/{name}/clear", responses={**_NOT_FOUND, 422: {"description": "a box of the wrong dimension, not "
                                                                             "finite, or min above max"}})
async def clear_region(name: MapNamePath, body: ClearRegion, service: ServiceDep) -> Cleared:
    """Set every cell of a box back to never observed (risk 0.5), as octomap_server's ``clear_bbx``: furniture
    that moved, a person who stood still. Durable before the answer, replayed at every start; blocks left
    holding nothing are freed."""
    result = await service.writes.add_edit(name, Clear(tuple(body.min), tuple(body.max)))
    return Cleared(cells_cleared=result.cells_updated, version=result.version)


@router.delete("/{name}", status_code=204, response_class=Response, responses=_NOT_FOUND)
async def delete_map(name: MapNamePath, service: ServiceDep) -> Response:
    """Delete a map and everything stored about it (after a batch in flight finishes)."""
    await service.maps.delete_map(name)
    return Response(status_code=204)
