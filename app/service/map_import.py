"""A map started from a saved map (``POST /maps/import``): a Nav2 ``map.yaml`` + image, or a ``nav_msgs/OccupancyGrid``.

The steps, each before the work it guards:

1. the Content-Type, and the name (409 when taken), before the body is read;
2. the file opened in a thread (``app.formats.saved_maps``, ``app.ros.grid_in``): its geometry read and
   checked, the image's cells from its header (``FUZZYRISK_MAX_MAP_CELLS``), before any pixel is decoded;
3. the new map checked as ``POST /maps`` checks one (the name again, ``FUZZYRISK_MAX_MAPS``,
   ``FUZZYRISK_MAX_TOTAL_CELLS``), then the cells decoded;
4. the map created, and the cells fused as its first batch (``WritePath.add_prior``: committed, then
   applied, as a scan batch is; replayed at every start). Should that fail, the map is deleted
   again: an import makes a whole map or nothing. Once the body is in, a client that goes away does
   not stop it half-way.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator

from anyio import to_thread
from pydantic import ValidationError

from app.errors import Invalid, UnsupportedMediaType
from app.formats import saved_maps
from app.formats.saved_maps import MapCells, SavedMap
from app.maps import shielded
from app.ros import grid_in
from app.ros.messages_out import CDR_MEDIA_TYPE
from app.schemas import DEFAULT_FRAME_ID, MapCreate, MapImport, MapInfo, check_frame_id
from app.service.mapservice import MapService

LOG = logging.getLogger("fuzzyrisk.maps")

JSON = "application/json"
#: Every accepted Content-Type: a Nav2 map zipped or as a form, an OccupancyGrid as JSON or CDR.
MEDIA_TYPES = (saved_maps.ZIP, saved_maps.X_ZIP, saved_maps.MULTIPART, JSON, CDR_MEDIA_TYPE)


async def import_map(service: MapService, query: MapImport, *, content_type: str,
                     body: AsyncIterator[bytes]) -> MapInfo:
    """Create the map ``query.name`` from the saved map ``body`` (of ``content_type``): the map at its first version."""
    media = content_type.split(";")[0].strip().lower()
    if media not in {m.lower() for m in MEDIA_TYPES}:
        raise UnsupportedMediaType(
            f"Content-Type {media!r} is not a saved map: send a Nav2 map.yaml and its image zipped "
            f"({saved_maps.ZIP}) or as a form ({saved_maps.MULTIPART}, parts '{saved_maps.YAML_PART}' and "
            f"'{saved_maps.IMAGE_PART}'), or a nav_msgs/OccupancyGrid as {JSON} or {CDR_MEDIA_TYPE}")
    await service.maps.check_name(query.name)
    data = b"".join([chunk async for chunk in body])  # bounded while it arrives (FUZZYRISK_MAX_BODY_BYTES)
    settings = service.settings
    saved = await to_thread.run_sync(_open, data, content_type, media, settings.max_map_cells, settings.max_body_bytes)
    request = _map_create(query, saved)
    await service.maps.check_new(request)
    cells = await to_thread.run_sync(saved.cells)
    del data
    return await shielded(_create(service, request, cells, query.prior_scans))


def _open(data: bytes, content_type: str, media: str, max_cells: int, max_file_bytes: int) -> SavedMap:
    if media == JSON:
        return grid_in.open_json(data, max_cells=max_cells)
    if media == CDR_MEDIA_TYPE.lower():
        return grid_in.open_cdr(data, max_cells=max_cells)
    return saved_maps.open_nav2(data, content_type, max_cells=max_cells, max_file_bytes=max_file_bytes)


def _map_create(query: MapImport, saved: SavedMap) -> MapCreate:
    """The new map: the file's grid, the query's settings; its frame the query's, else the file's, else ``map``."""
    frame_id = query.frame_id
    if frame_id is None and saved.frame_id is not None:
        try:
            frame_id = check_frame_id(saved.frame_id)
        except ValueError as exc:
            raise Invalid(f"body: header.frame_id: {exc}; or give the map's frame_id in the query") from None
    try:
        return MapCreate(name=query.name, resolution=saved.resolution, origin=list(saved.origin),
                         size=[saved.width * saved.resolution, saved.height * saved.resolution], model=query.model,
                         sensor=query.sensor(), engine=query.engine, frame_id=frame_id or DEFAULT_FRAME_ID)
    except ValidationError as exc:  # the file's grid was checked when it was opened: cannot happen
        raise Invalid(f"body: the saved map's grid cannot be a map ({exc.errors()[0]['msg']})") from None


async def _create(service: MapService, request: MapCreate, cells: MapCells, weight: int) -> MapInfo:
    """Create the map and fuse the cells as its first batch; delete it again if that fails."""
    entry = await service.maps.create(request)
    try:
        await service.writes.add_prior(request.name, entry.incarnation, cells, weight)
    except BaseException:
        try:
            await service.maps.discard(request.name, entry.incarnation)
        except Exception:  # noqa: BLE001 - the import's own error is the answer; this one is logged
            LOG.exception("map %s: an import failed and its map could not be deleted again", request.name)
        raise
    return await service.reads.map_info(request.name)

