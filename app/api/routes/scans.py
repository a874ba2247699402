"""Scan batches in (JSON, or one binary scan), and the last scan out (for the web page)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response

from app.formats import etags
from app.scans import BINARY_TYPES
from app.api.deps import MapNamePath, ServiceDep
from app.ros.messages_in import MSGTYPES, media_type
from app.schemas import EXAMPLE_CLOUD, EXAMPLE_LASER, SCAN_QUERY_DOC, SCAN_QUERY_FIELDS, BatchResult, LastScan

router = APIRouter(prefix="/maps", tags=["scans"])

_BINARY_DOC = """\
**JSON** (`application/json`): a `ScanBatch`, applied in order, all or nothing. Ranges follow
REP 117: `null`, `NaN`, `-inf` and ranges below `range_min` are skipped; `+inf` or a range at or
above `range_max` is a no-return (free space up to `range_max`). JSON has no infinities: send
`"inf"`, `"-inf"`, `"nan"` as strings (or Python's `Infinity`/`NaN` tokens).

**Binary** (`application/x-npy` or `application/octet-stream`): one scan per request, the body a
`.npy` file (float32 or float64, read with `allow_pickle=False`) or raw little-endian float32;
the pose and scan parameters go in the query:

* 3-D map: points in the sensor frame, `.npy` of shape (N, 3), or raw points of `point_step` bytes
  each (x, y, z little-endian float32 at its start: `point_step=12` packed, 16 with an intensity;
  without it a raw body is refused, its layout unknown); query `x, y, z` (sensor position), `qx, qy,
  qz, qw` (orientation, default identity), `range_max`.
* 2-D map, LaserScan: raw float32 ranges (or a 1-D `.npy`); query `x, y, theta, angle_min,
  angle_increment, range_min, range_max`.
* 2-D map, points: `.npy` of shape (N, 2) in the sensor frame; query `x, y, theta, range_max`.

**A ROS 2 message** (`application/vnd.ros2.sensor_msgs.msg.LaserScan+cdr` or
`application/vnd.ros2.sensor_msgs.msg.PointCloud2+cdr`): one CDR-serialized message (the bytes of
`rclpy.serialization.serialize_message`), the pose of its `frame_id` in the map frame in the query as
`x, y, z, qx, qy, qz, qw` (all seven); a PointCloud2 also takes `range_max`. A LaserScan on a 2-D map
needs a level scanner (z up, or down when mounted upside down); on a 3-D map any mounting.

`registration_sigma` (metres) is optional in every form. The answer comes once the batch is on
disk (fsync) and applied; `version` is the map's new version.
"""

_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {
                "schema": {"$ref": "#/components/schemas/ScanBatch"},
                "examples": {
                    "laser": {"summary": "a LaserScan on a 2-D map", "value": {"scans": [EXAMPLE_LASER]}},
                    "cloud": {"summary": "a point cloud on a 3-D map", "value": {"scans": [EXAMPLE_CLOUD]}},
                },
            },
            **{media: {"schema": {"type": "string", "format": "binary"}} for media in BINARY_TYPES},
            **{media_type(t): {"schema": {"type": "string", "format": "binary"}} for t in MSGTYPES},
        },
    }
}

# The query (app.schemas.ScanQuery) is validated with the body by the service; documented here as
# FastAPI documents an optional float query parameter.
_BODY["parameters"] = [
    {
        "name": field, "in": "query", "required": False, "description": SCAN_QUERY_DOC,
        "schema": {"anyOf": [{"type": "number"}, {"type": "null"}], "description": SCAN_QUERY_DOC,
                   "title": field.replace("_", " ").title()},
    }
    for field in SCAN_QUERY_FIELDS
]


@router.post(
    "/{name}/scans",
    openapi_extra=_BODY,
    description=_BINARY_DOC,
    responses={
        404: {"description": "no map of that name"},
        413: {"description": "body, batch or scan larger than the configured limits"},
        415: {"description": "a Content-Type other than JSON or the binary types"},
        503: {"description": "the map already holds FUZZYRISK_MAX_PENDING_BATCHES batches in line, or the "
                             "data directory is full or read-only (see Retry-After)"},
    },
)
async def post_scans(name: MapNamePath, request: Request, service: ServiceDep) -> BatchResult:
    """Fuse a batch of scans into the map."""
    async with service.writes.receiving(name):  # counted against the map's line from the first byte
        body = await request.body()
    return await service.writes.add_scans(
        name, body=body, content_type=request.headers.get("content-type", ""), query=request.query_params
    )


@router.get("/{name}/scans/last", responses={404: {"description": "no such map, or no scan yet"}})
async def last_scan(name: MapNamePath, service: ServiceDep, response: Response) -> LastScan:
    """Beam ends of the last scan fused (map frame, at most 4096): the web page draws them."""
    scan = await service.reads.last_scan(name)
    response.headers[etags.VERSION_HEADER] = str(scan.version)
    return scan
