"""The risk grid out: JSON, .npy, PNG, point queries, and ROS exports (Nav2 map files, OccupancyGrid)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response
from pydantic import FiniteFloat

from app.deps import MapNamePath, ServiceDep
from app.errors import Invalid
from app.exports import NAV2_FREE_THRESH, NAV2_OCCUPIED_THRESH
from app.schemas import OccupancyGrid, RiskQuery, RiskValues

router = APIRouter(prefix="/maps", tags=["risk"])

ZBand = Annotated[
    FiniteFloat | None, Query(description="3-D maps: project the cells whose centre lies in [z_min, z_max], metres")
]
Threshold = Annotated[float, Query(ge=0.0, le=1.0, allow_inf_nan=False)]
_NOT_FOUND = {404: {"description": "no map of that name"}}


def _grid_headers(name: str, version: int, resolution: float, origin: tuple[float, ...]) -> dict[str, str]:
    return {
        "X-Map-Name": name,
        "X-Map-Version": str(version),
        "X-Map-Resolution": repr(resolution),
        "X-Map-Origin": ",".join(repr(v) for v in origin),
    }


@router.get(
    "/{name}/risk",
    response_class=Response,
    responses={
        **_NOT_FOUND,
        200: {
            "description": "json: RiskGridJSON; npy: float32 risk (layer=risk) or bool observed mask "
            "(layer=observed) of shape (nx, ny[, nz]), index [i, j(, k)] along x, y(, z); png: one pixel a "
            "cell (scale x scale), top row = highest y",
            "content": {
                "application/json": {"schema": {"$ref": "#/components/schemas/RiskGridJSON"}},
                "application/x-npy": {"schema": {"type": "string", "format": "binary"}},
                "image/png": {"schema": {"type": "string", "format": "binary"}},
            },
        },
    },
)
async def get_risk(
    name: MapNamePath,
    service: ServiceDep,
    format: Literal["json", "npy", "png"] = "json",
    layer: Annotated[
        Literal["risk", "observed"],
        Query(description="npy: `risk` (float32) or `observed` (bool: True where a beam ever reached the cell)"),
    ] = "risk",
    scale: Annotated[int, Query(ge=1, le=64, description="png: pixels per cell")] = 1,
    z_min: ZBand = None,
    z_max: ZBand = None,
) -> Response:
    """The defuzzified risk of every cell (0.5 = unknown) as JSON, ``.npy`` or a PNG a person can read.

    ``format=npy&layer=observed``: the observed mask beside the ``.npy`` risk, a bool array of the
    same shape and order (the JSON grid carries it as ``observed``; the PNG draws it grey-blue).
    PNG colours: white (risk 0) through yellow, orange and red to dark crimson (risk 1); cells no
    beam ever reached are grey-blue, hatched at ``scale >= 4``. A 3-D map is drawn as the
    largest risk of the observed cells of each column within ``[z_min, z_max]``.
    """
    if layer == "observed" and format != "npy":
        raise Invalid(f"layer=observed is for format=npy; format={format} has the observed cells already "
                      "(json: `observed`, png: grey-blue)")
    if format == "json":
        return Response(await service.risk_json(name), media_type="application/json")
    if format == "npy":
        data, grid = await service.risk_npy(name, layer)
        headers = _grid_headers(name, grid.version, grid.spec.resolution, grid.spec.origin)
        headers["Content-Disposition"] = f'attachment; filename="{name}-{layer}-v{grid.version}.npy"'
        return Response(data, media_type="application/x-npy", headers=headers)
    data, grid = await service.risk_png(name, scale=scale, z_min=z_min, z_max=z_max)
    return Response(data, media_type="image/png",
                    headers=_grid_headers(name, grid.version, grid.spec.resolution, grid.spec.origin))


@router.post("/{name}/risk/query", responses=_NOT_FOUND)
async def query_risk(name: MapNamePath, body: RiskQuery, service: ServiceDep) -> RiskValues:
    """Risk of the cells holding the given points (each must lie inside the map)."""
    return await service.risk_at(name, body.points)


@router.get("/{name}/occupancy_grid", responses=_NOT_FOUND)
async def occupancy_grid(
    name: MapNamePath,
    service: ServiceDep,
    mode: Literal["trinary", "scale", "probability"] = "trinary",
    free_thresh: Threshold = NAV2_FREE_THRESH,
    occupied_thresh: Threshold = NAV2_OCCUPIED_THRESH,
    z_min: ZBand = None,
    z_max: ZBand = None,
) -> OccupancyGrid:
    """The map as a ``nav_msgs/OccupancyGrid`` (frame ``map``): ``data[j * width + i]``, -1 unknown.

    The grid map_server would publish from ``export/nav2`` with the same mode and thresholds:
    ``trinary`` (the default, as map_server's): 100 above ``occupied_thresh`` (0.6, the planner's
    default ``max_risk``), 0 below ``free_thresh`` (0.45), else -1; ``scale``: 100 above, 0 below,
    graded 0..100 between, with Nav2 Jazzy's arithmetic (float32, halves rounded away from zero);
    ``probability``: raw ``round(100 * risk)``, what map_server loads from the ``raw`` export;
    below risk 0.995 never 100, so not for a costmap with Nav2's defaults. A 3-D map is projected
    over ``[z_min, z_max]`` as octomap_server's projected map.
    """
    return await service.occupancy_grid(name, mode=mode, free_thresh=free_thresh, occupied_thresh=occupied_thresh,
                                        z_min=z_min, z_max=z_max)


@router.get(
    "/{name}/export/nav2",
    response_class=Response,
    responses={**_NOT_FOUND, 200: {"content": {"application/zip": {"schema": {"type": "string", "format": "binary"}}}}},
)
async def export_nav2(
    name: MapNamePath,
    service: ServiceDep,
    mode: Literal["trinary", "scale", "raw"] = "trinary",
    format: Literal["pgm", "png"] = "pgm",
    free_thresh: Threshold = NAV2_FREE_THRESH,
    occupied_thresh: Threshold = NAV2_OCCUPIED_THRESH,
    z_min: ZBand = None,
    z_max: ZBand = None,
) -> Response:
    """A zip of ``map.yaml`` + ``map.pgm`` (or ``.png``) for Nav2's map_server (``yaml_filename``).

    map_server publishes exactly ``occupancy_grid`` of the same mode (``probability`` for ``raw``),
    unknown cells included. ``trinary``: occupied black, free white, the rest a grey that reads
    back as unknown. ``scale`` (PNG only): grey = 255 * (1 - risk), so Nav2 keeps the grades
    between the thresholds; unknown cells are transparent, map_server's only unknown in scale
    mode (a PGM has no alpha, hence 422). ``raw``: the pixel is ``round(100 * risk)``, unknown
    255 (map_server copies 0..100, reads the rest as -1; thresholds are written but unused).
    Nav2's static layer flattens a graded map unless ``trinary_costmap: false``.
    """
    data = await service.nav2_zip(
        name, mode=mode, image_format=format, free_thresh=free_thresh, occupied_thresh=occupied_thresh,
        z_min=z_min, z_max=z_max,
    )
    return Response(data, media_type="application/zip",
                    headers={"Content-Disposition": f'attachment; filename="{name}-nav2.zip"'})

