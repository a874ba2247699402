"""The risk grid out: JSON, .npy, PNG, point queries, and ROS exports (Nav2 map files, OccupancyGrid)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Header, Path, Query, Response
from pydantic import FiniteFloat

from app.formats import etags
from app.ros import messages_out
from app.api.deps import MapNamePath, ServiceDep
from app.errors import Invalid
from app.api.largebody import bytes_response
from app.formats.exports import NAV2_FREE_THRESH, NAV2_OCCUPIED_THRESH
from app.formats.mediatypes import MCAP, OCTET_STREAM
from app.schemas import GridWindow, OccupancyGrid, RiskQuery, RiskValues, WindowCorner
from app.maps import GridSnapshot, GridStamp
from app.service.mapservice import MapService

router = APIRouter(prefix="/maps", tags=["risk"])

ZBand = Annotated[
    FiniteFloat | None, Query(description="3-D maps: project the cells whose centre lies in [z_min, z_max], metres")
]
Threshold = Annotated[float, Query(ge=0.0, le=1.0, allow_inf_nan=False)]
_NOT_FOUND = {404: {"description": "no map of that name"}}
IfNoneMatch = Annotated[
    str | None,
    Header(description="an ETag of an earlier answer of this route and query: 304 with no body while the map is at "
           "that version"),
]
#: The corner of an answer's first cell, and its cells along each axis: what .npy and PNG have no field for.
ORIGIN_HEADER = "X-Map-Origin"
SHAPE_HEADER = "X-Map-Shape"
#: The headers every grid answer carries (on a 200; a 304 carries ETag and X-Map-Version).
_GRID_HEADERS = {
    "ETag": {"description": "strong; changes with the map version and with the format and query (the window "
             "included)", "schema": {"type": "string"}},
    etags.VERSION_HEADER: {"description": "the map version of the answer", "schema": {"type": "integer"}},
    ORIGIN_HEADER: {"description": "the corner of the answer's first cell (index 0 along each axis), metres, "
                    "comma-separated x,y[,z] (the window's when one is asked for)",
                    "schema": {"type": "string"}, "example": "-8.0,-5.0"},
    SHAPE_HEADER: {"description": "the answer's cells along x,y[,z], comma-separated (the .npy array's shape; a "
                   "PNG is ny rows of nx pixels, times scale)", "schema": {"type": "string"}, "example": "320,200"},
}
_NOT_MODIFIED = {304: {"description": "If-None-Match names the current ETag: the answer would be the same bytes "
                       "(no body)", "headers": _GRID_HEADERS}}


def _grid_headers(name: str, grid: GridSnapshot | GridStamp, variant: dict[str, object]) -> dict[str, str]:
    return {
        "ETag": grid.etag(variant),
        "X-Map-Name": name,
        etags.VERSION_HEADER: str(grid.version),
        "X-Map-Frame": grid.frame_id,
        "X-Map-Resolution": repr(grid.spec.resolution),
        ORIGIN_HEADER: ",".join(repr(v) for v in grid.spec.origin),
        SHAPE_HEADER: ",".join(str(n) for n in grid.spec.shape),
    }


async def grid_window(
    low: Annotated[WindowCorner | None, Query(
        alias="min", description="the window's low corner `x,y` or `x,y,z`, metres: the read covers the cells that "
        "meet [min, max], cut to the map (left out: the map's own edge)", examples=["-2.0,-1.5"])] = None,
    high: Annotated[WindowCorner | None, Query(
        alias="max", description="the window's high corner `x,y` or `x,y,z`, metres (left out: the map's own edge)",
        examples=["2.0,1.5"])] = None,
) -> GridWindow:
    """The window of a grid read, from its query (``?min=x,y[,z]&max=x,y[,z]``)."""
    return GridWindow(min=low, max=high)


WindowQuery = Annotated[GridWindow, Depends(grid_window)]


async def _unchanged(
    service: MapService, name: str, variant: dict[str, object], if_none_match: str | None
) -> Response | None:
    """304 when ``If-None-Match`` names the ETag this read would carry now (decided before any grid is read)."""
    if not if_none_match:
        return None
    etag, version = await service.reads.current_etag(name, variant)
    return etags.not_modified(etag, version) if etags.matches(if_none_match, etag) else None


_BINARY = {"schema": {"type": "string", "format": "binary"}}
Accept = Annotated[str | None, Header(description=f"`{OCTET_STREAM}` alone: the same bytes labelled so (what "
                                                  "generic HTTP clients and client generators handle)")]
LayerQuery = Annotated[
    Literal["risk", "observed"],
    Query(description="`risk` (float32) or `observed` (bool: True where a beam ever reached the cell)"),
]
ScaleQuery = Annotated[int, Query(ge=1, le=64, description="pixels per cell")]


def _binary_200(media_type: str, description: str) -> dict[int | str, dict[str, Any]]:
    """A binary answer in its own media type, or as application/octet-stream when only that is accepted."""
    return {200: {"description": description, "headers": _GRID_HEADERS,
                  "content": {media_type: _BINARY, OCTET_STREAM: _BINARY}}}


def _media_type(accept: str | None, native: str) -> str:
    """``native``, unless the client accepts application/octet-stream and neither ``native`` nor a wildcard."""
    ranges = {part.split(";")[0].strip().lower() for part in (accept or "").split(",")}
    kind = native.split("/")[0]
    if OCTET_STREAM in ranges and not ranges & {native, "*/*", f"{kind}/*"}:
        return OCTET_STREAM
    return native


@router.get(
    "/{name}/risk",
    response_class=Response,
    responses={
        **_NOT_FOUND,
        **_NOT_MODIFIED,
        200: {
            "description": "RiskGridJSON (format=npy and format=png: see get_risk_npy and get_risk_png)",
            "headers": _GRID_HEADERS,
            "content": {
                "application/json": {"schema": {"$ref": "#/components/schemas/RiskGridJSON"}},
                "application/x-npy": _BINARY,
                "image/png": _BINARY,
            },
        },
    },
)
async def get_risk(
    name: MapNamePath,
    service: ServiceDep,
    window: WindowQuery,
    format: Annotated[
        Literal["json", "npy", "png"],
        Query(description="json; npy and png are shorthands of `GET /maps/{name}/risk.npy` and `.png`, whose "
              "answers the OpenAPI document declares as binary (generated clients: use those)"),
    ] = "json",
    layer: Annotated[LayerQuery, Query(description="format=npy: see get_risk_npy")] = "risk",
    scale: Annotated[ScaleQuery, Query(description="format=png: pixels per cell")] = 1,
    z_min: ZBand = None,
    z_max: ZBand = None,
    if_none_match: IfNoneMatch = None,
) -> Response:
    """The defuzzified risk of every cell (0.5 = unknown) as JSON (``RiskGridJSON``: the grid, the
    observed cells, the map's frame and version), or of the cells of a window (``min``, ``max``)."""
    if layer == "observed" and format != "npy":
        raise Invalid(f"layer=observed is for format=npy; format={format} has the observed cells already "
                      "(json: `observed`, png: grey-blue)")
    if format == "npy":
        return await _risk_npy(name, service, layer, window, if_none_match, "application/x-npy")
    if format == "png":
        return await _risk_png(name, service, scale, z_min, z_max, window, if_none_match, "image/png")
    variant: dict[str, object] = {"read": "risk", "format": format, "layer": layer, "scale": scale, "z_min": z_min,
                                  "z_max": z_max, **window.variant()}
    if (unchanged := await _unchanged(service, name, variant, if_none_match)) is not None:
        return unchanged
    data, grid = await service.reads.risk_json(name, window)
    return bytes_response(data, media_type="application/json", headers=_grid_headers(name, grid, variant))


async def _risk_npy(name: str, service: MapService, layer: str, window: GridWindow, if_none_match: str | None,
                    media_type: str) -> Response:
    variant: dict[str, object] = {"read": "risk", "format": "npy", "layer": layer, "scale": 1, "z_min": None,
                                  "z_max": None, "media_type": media_type, **window.variant()}
    if (unchanged := await _unchanged(service, name, variant, if_none_match)) is not None:
        return unchanged
    data, grid, sent = await service.reads.risk_npy(name, layer, window)
    headers = _grid_headers(name, grid, variant)
    headers["Content-Disposition"] = f'attachment; filename="{name}-{layer}-v{grid.version}.npy"'
    return bytes_response(data, media_type=media_type, headers=headers, on_sent=sent)


async def _risk_png(name: str, service: MapService, scale: int, z_min: float | None, z_max: float | None,
                    window: GridWindow, if_none_match: str | None, media_type: str) -> Response:
    variant: dict[str, object] = {"read": "risk", "format": "png", "layer": "risk", "scale": scale, "z_min": z_min,
                                  "z_max": z_max, "media_type": media_type, **window.variant()}
    if (unchanged := await _unchanged(service, name, variant, if_none_match)) is not None:
        return unchanged
    data, grid, sent = await service.reads.risk_png(name, scale=scale, z_min=z_min, z_max=z_max, region=window)
    return bytes_response(data, media_type=media_type, headers=_grid_headers(name, grid, variant), on_sent=sent)


@router.get(
    "/{name}/risk.npy",
    response_class=Response,
    responses={**_NOT_FOUND, **_NOT_MODIFIED, **_binary_200(
        "application/x-npy", "a .npy file: float32 risk (layer=risk) or the bool observed mask (layer=observed), "
        "shape (nx, ny[, nz]) as X-Map-Shape says, index [i, j(, k)] along x, y(, z) from X-Map-Origin")},
)
async def get_risk_npy(name: MapNamePath, service: ServiceDep, window: WindowQuery, layer: LayerQuery = "risk",
                       if_none_match: IfNoneMatch = None, accept: Accept = None) -> Response:
    """The risk grid as a ``.npy`` file (``numpy.load(..., allow_pickle=False)``), or the observed mask.

    ``layer=observed``: the observed mask beside the risk, a bool array of the same shape and
    order: True where a beam ever reached the cell. The file has no field for the grid's place:
    ``X-Map-Origin`` (the corner of cell ``[0, 0(, 0)]``, metres) and ``X-Map-Shape`` say it.
    """
    return await _risk_npy(name, service, layer, window, if_none_match, _media_type(accept, "application/x-npy"))


@router.get(
    "/{name}/risk.png",
    response_class=Response,
    responses={**_NOT_FOUND, **_NOT_MODIFIED, **_binary_200(
        "image/png", "one pixel a cell (scale x scale), top row = highest y; X-Map-Origin is the corner of the "
        "bottom-left pixel's cell")},
)
async def get_risk_png(name: MapNamePath, service: ServiceDep, window: WindowQuery, scale: ScaleQuery = 1,
                       z_min: ZBand = None, z_max: ZBand = None, if_none_match: IfNoneMatch = None,
                       accept: Accept = None) -> Response:
    """The risk grid as a picture a person can read.

    Colours: white (risk 0) through yellow, orange and red to dark crimson (risk 1); cells no
    beam ever reached are grey-blue, hatched at ``scale >= 4``. A 3-D map is drawn as the
    largest risk of the observed cells of each column within ``[z_min, z_max]``.
    """
    return await _risk_png(name, service, scale, z_min, z_max, window, if_none_match,
                           _media_type(accept, "image/png"))


@router.post("/{name}/risk/query", responses=_NOT_FOUND)
async def query_risk(name: MapNamePath, body: RiskQuery, service: ServiceDep, response: Response) -> RiskValues:
    """Risk of the cells holding the given points (each must lie inside the map)."""
    values = await service.reads.risk_at(name, body.points)
    response.headers[etags.VERSION_HEADER] = str(values.version)
    return values


_OGRID_DOC = """

    The grid map_server would publish from ``export/nav2`` with the same mode and thresholds:
    ``trinary`` (the default, as map_server's): 100 above ``occupied_thresh`` (0.6, the planner's
    default ``max_risk``), 0 below ``free_thresh`` (0.45), else -1; ``scale``: 100 above, 0 below,
    graded 0..100 between, with Nav2 Jazzy's arithmetic (float32, halves rounded away from zero);
    ``probability``: raw ``round(100 * risk)``, what map_server loads from the ``raw`` export;
    below risk 0.995 never 100, so not for a costmap with Nav2's defaults. A 3-D map is projected
    over ``[z_min, z_max]`` as octomap_server's projected map. ``header.stamp`` and
    ``info.map_load_time`` are the time of the map's last batch (its creation before one), so
    every read of one version is the same bytes.
    """
GridMode = Literal["trinary", "scale", "probability"]
_OGRID_MEDIA = {"json": "application/json", "cdr": messages_out.CDR_MEDIA_TYPE, "mcap": MCAP}


async def _occupancy_grid(name: str, service: MapService, format: str, mode: str, free_thresh: float,
                          occupied_thresh: float, z_min: float | None, z_max: float | None, window: GridWindow,
                          if_none_match: str | None, media_type: str) -> Response:
    variant: dict[str, object] = {"read": "occupancy_grid", "format": format, "mode": mode,
                                  "free_thresh": free_thresh, "occupied_thresh": occupied_thresh, "z_min": z_min,
                                  "z_max": z_max, "media_type": media_type, **window.variant()}
    if (unchanged := await _unchanged(service, name, variant, if_none_match)) is not None:
        return unchanged
    data, grid, sent = await service.reads.occupancy_grid(name, mode=mode, free_thresh=free_thresh,
                                              occupied_thresh=occupied_thresh, z_min=z_min, z_max=z_max,
                                              encoding=format, region=window)
    headers = _grid_headers(name, grid, variant)
    if format == "mcap":
        headers["Content-Disposition"] = f'attachment; filename="{name}-v{grid.version}.mcap"'
    return bytes_response(data, media_type=media_type, headers=headers, on_sent=sent)


@router.get(
    "/{name}/occupancy_grid",
    response_model=OccupancyGrid,  # the JSON answer's schema; the route writes every format's bytes itself
    responses={
        **_NOT_FOUND,
        **_NOT_MODIFIED,
        200: {
            "description": "OccupancyGrid (plus the map version); format=cdr and format=mcap: see "
            "occupancy_grid_file",
            "headers": _GRID_HEADERS,
            "content": {messages_out.CDR_MEDIA_TYPE: _BINARY, MCAP: _BINARY},
        },
    },
)
async def occupancy_grid(
    name: MapNamePath,
    service: ServiceDep,
    window: WindowQuery,
    mode: GridMode = "trinary",
    format: Annotated[
        Literal["json", "cdr", "mcap"],
        Query(description="json; cdr and mcap are shorthands of `GET /maps/{name}/occupancy_grid.cdr` and "
              "`.mcap` (occupancy_grid_file), whose answers the OpenAPI document declares as binary (generated "
              "clients: use that)"),
    ] = "json",
    free_thresh: Threshold = NAV2_FREE_THRESH,
    occupied_thresh: Threshold = NAV2_OCCUPIED_THRESH,
    z_min: ZBand = None,
    z_max: ZBand = None,
    if_none_match: IfNoneMatch = None,
) -> Response:
    """The map as a ``nav_msgs/OccupancyGrid`` in the map's frame (the message's fields, plus
    ``version``): ``data[j * width + i]``, -1 unknown. JSON up to 4,000,000 cells (422 beyond: the
    ``.cdr`` and ``.mcap`` forms carry any size). A window (``min``, ``max``) gives its cells only,
    ``info.origin`` its corner."""
    return await _occupancy_grid(name, service, format, mode, free_thresh, occupied_thresh, z_min, z_max, window,
                                 if_none_match, _OGRID_MEDIA[format])


occupancy_grid.__doc__ = (occupancy_grid.__doc__ or "") + _OGRID_DOC


@router.get(
    "/{name}/occupancy_grid.{encoding}",
    response_class=Response,
    responses={**_NOT_FOUND, **_NOT_MODIFIED, 200: {
        "description": f"cdr: the nav_msgs/msg/OccupancyGrid CDR serialized (what "
        f"rclpy.serialization.serialize_message writes); mcap: an MCAP file holding it on {messages_out.MAP_TOPIC}",
        "headers": _GRID_HEADERS,
        "content": {messages_out.CDR_MEDIA_TYPE: _BINARY, MCAP: _BINARY, OCTET_STREAM: _BINARY}}},
)
async def occupancy_grid_file(
    name: MapNamePath,
    encoding: Annotated[Literal["cdr", "mcap"], Path(description="cdr or mcap")],
    service: ServiceDep,
    window: WindowQuery,
    mode: GridMode = "trinary",
    free_thresh: Threshold = NAV2_FREE_THRESH,
    occupied_thresh: Threshold = NAV2_OCCUPIED_THRESH,
    z_min: ZBand = None,
    z_max: ZBand = None,
    if_none_match: IfNoneMatch = None,
    accept: Accept = None,
) -> Response:
    """The map's ``nav_msgs/msg/OccupancyGrid`` as ROS 2 bytes: ``cdr``, serialized as ROS 2 does (for
    ``rclpy.serialization.deserialize_message`` or a rosbags typestore), or ``mcap``, a file with
    that one message on ``/map`` (latched QoS as map_server's) for Foxglove or a bag player."""
    return await _occupancy_grid(name, service, encoding, mode, free_thresh, occupied_thresh, z_min, z_max, window,
                                 if_none_match, _media_type(accept, _OGRID_MEDIA[encoding]))


occupancy_grid_file.__doc__ = (occupancy_grid_file.__doc__ or "") + _OGRID_DOC


@router.get(
    "/{name}/export/nav2",
    response_class=Response,
    responses={**_NOT_FOUND, **_NOT_MODIFIED,
               **_binary_200("application/zip", "map.yaml and the image, zipped")},
)
async def export_nav2(
    name: MapNamePath,
    service: ServiceDep,
    window: WindowQuery,
    mode: Literal["trinary", "scale", "raw"] = "trinary",
    format: Literal["pgm", "png"] = "pgm",
    free_thresh: Threshold = NAV2_FREE_THRESH,
    occupied_thresh: Threshold = NAV2_OCCUPIED_THRESH,
    z_min: ZBand = None,
    z_max: ZBand = None,
    if_none_match: IfNoneMatch = None,
    accept: Accept = None,
) -> Response:
    """A zip of ``map.yaml`` + ``map.pgm`` (or ``.png``) for Nav2's map_server (``yaml_filename``).

    map_server publishes exactly ``occupancy_grid`` of the same mode (``probability`` for ``raw``),
    unknown cells included. ``trinary``: occupied black, free white, the rest a grey that reads
    back as unknown. ``scale`` (PNG only): grey = 255 * (1 - risk), so Nav2 keeps the grades
    between the thresholds; unknown cells are transparent, map_server's only unknown in scale
    mode (a PGM has no alpha, hence 422). ``raw``: the pixel is ``round(100 * risk)``, unknown
    255 (map_server copies 0..100, reads the rest as -1; thresholds are written but unused).
    Nav2's static layer flattens a graded map unless ``trinary_costmap: false``. map_server's YAML
    has no frame: ``map.yaml`` names the map's in a comment, for map_server's ``frame_id`` parameter.
    A window (``min``, ``max``) exports its cells only, ``origin`` in ``map.yaml`` its corner.
    """
    media_type = _media_type(accept, "application/zip")
    variant: dict[str, object] = {"read": "export/nav2", "format": format, "mode": mode, "free_thresh": free_thresh,
                                  "occupied_thresh": occupied_thresh, "z_min": z_min, "z_max": z_max,
                                  "media_type": media_type, **window.variant()}
    if (unchanged := await _unchanged(service, name, variant, if_none_match)) is not None:
        return unchanged
    data, grid, sent = await service.reads.nav2_zip(
        name, mode=mode, image_format=format, free_thresh=free_thresh, occupied_thresh=occupied_thresh,
        z_min=z_min, z_max=z_max, region=window,
    )
    headers = _grid_headers(name, grid, variant)
    headers["Content-Disposition"] = f'attachment; filename="{name}-nav2.zip"'
    return bytes_response(data, media_type=media_type, headers=headers, on_sent=sent)

