"""A recorded bag in: ``POST /maps/{name}/bags`` imports a ROS 1 ``.bag`` or a single-file ``.mcap`` into a map
(``app.service.bag_upload``)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request

from app.service import bag_upload
from app.api.deps import MapNamePath, ServiceDep
from app.ros.bags import DEFAULT_CLOUD_RANGE_MAX_M
from app.formats.mediatypes import MCAP, OCTET_STREAM, ROSBAG, X_MCAP
from app.schemas import BagImportResult

router = APIRouter(prefix="/maps", tags=["scans"])

_DOC = f"""\
The body is one bag file: a ROS 1 `.bag` (`Content-Type: {ROSBAG}`) or a rosbag2 `.mcap` file
(`{MCAP}`, or `{X_MCAP}`; the `.mcap` inside a bag directory; a sqlite3 bag converts with
`ros2 bag convert` or `rosbags-convert`); `{OCTET_STREAM}` is told by its first bytes.
Its LaserScan and PointCloud2 topics (or `topic`) are placed by `/tf` and `/tf_static`, interpolated
at each message's stamp along the chain from its frame to `map_frame` (default: the map's `frame_id`;
or by `pose_topic`), converted as CDR bodies are, and fused in recorded order in batches of at most
`FUZZYRISK_MAX_SCANS_PER_BATCH`, each durable before the next is read. A message that cannot be
placed or used is skipped and counted in `skipped` by reason. The body is bounded by
`FUZZYRISK_MAX_BODY_BYTES`, what its chunks decompress to by `FUZZYRISK_MAX_BAG_BYTES`, each scan by
`FUZZYRISK_MAX_RAYS_PER_SCAN`.

The import is admitted once (a map with `FUZZYRISK_MAX_PENDING_BATCHES` batches in line answers 503
before the body is read, or at the first batch); its later batches are not refused for the line.
An error before the first batch is applied answers with its own status, and nothing was applied.
An error after it (a full disk, the map deleted or created again, a damaged chunk part-way) answers
**200** with `complete: false`, the error in `stopped` and what was applied (`batches`, `scans_fused`,
`version`): the applied batches are durable, so **do not send the bag again** (its first part would
be fused twice); import the rest another way, or delete the map and start over.
"""

_BODY: dict[str, Any] = {"requestBody": {"required": True, "content": {
    media: {"schema": {"type": "string", "format": "binary"}} for media in bag_upload.MEDIA_TYPES}}}


@router.post(
    "/{name}/bags",
    openapi_extra=_BODY,
    description=_DOC,
    responses={409: {"description": "the map was deleted and created again while the bag was read; nothing "
                                    "was applied"},
               503: {"description": "before any batch was applied (nothing was): the map's line is full "
                                    "(FUZZYRISK_MAX_PENDING_BATCHES), the data directory cannot take the body or the "
                                    "first batch (STORAGE_UNAVAILABLE), or the bodies in flight fill "
                                    "FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES; Retry-After"},
               415: {"description": f"a Content-Type other than {', '.join(bag_upload.MEDIA_TYPES)}"}},
)
async def post_bag(
    name: MapNamePath,
    request: Request,
    service: ServiceDep,
    map_frame: Annotated[str | None, Query(min_length=1, max_length=256, description="the frame the scans are "
                                           "placed in (default: the map's frame_id)")] = None,
    topic: Annotated[list[str] | None, Query(description="a topic to read (repeat; default: every LaserScan "
                                                               "and PointCloud2 topic)")] = None,
    pose_topic: Annotated[str | None, Query(description="a PoseStamped, PoseWithCovarianceStamped or Odometry "
                                                        "topic that places its frame instead of /tf")] = None,
    pose_frame: Annotated[str, Query(min_length=1, max_length=256, description="the frame a PoseStamped "
                                     "pose_topic places")] = "base_link",
    range_max: Annotated[float, Query(gt=0, le=1e4, description="a PointCloud2's range, metres")] = (
        DEFAULT_CLOUD_RANGE_MAX_M),
) -> BagImportResult:
    """Import a recorded bag's scans into the map."""
    return await bag_upload.import_upload(
        service, name, content_type=request.headers.get("content-type", ""), body=request.stream(),
        map_frame=map_frame, topics=tuple(topic or ()), pose_topic=pose_topic, pose_frame=pose_frame,
        range_max=range_max,
    )
