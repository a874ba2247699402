"""A recorded bag in: ``POST /maps/{name}/bags`` imports a ROS 1 ``.bag`` or a single-file ``.mcap`` into a map."""

from __future__ import annotations

import logging
import os
import tempfile
from collections import Counter
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from app import bagsize, import_bag
from app.batches import Limits
from app.deps import MapNamePath, ServiceDep
from app.errors import Invalid, ServiceError, TooLarge, UnsupportedMediaType

LOG = logging.getLogger("fuzzyrisk.bags")
router = APIRouter(prefix="/maps", tags=["scans"])

#: Content-Type -> (the file's first bytes, the suffix rosbags reads it by).
BAG_TYPES = {
    "application/x-rosbag": (b"#ROSBAG V2.0\n", ".bag"),
    "application/x-mcap": (b"\x89MCAP0\r\n", ".mcap"),
}
#: Also accepted (what generated clients send for a file): the container is told by its first bytes.
SNIFFED = "application/octet-stream"

_DOC = """\
The body is one bag file: a ROS 1 `.bag` (`Content-Type: application/x-rosbag`) or a rosbag2
`.mcap` file (`application/x-mcap`, the `.mcap` inside a bag directory; a sqlite3 bag converts with
`ros2 bag convert` or `rosbags-convert`); `application/octet-stream` is told by its first bytes.
Its LaserScan and PointCloud2 topics (or `topic`) are placed by `/tf` and `/tf_static`, interpolated
at each message's stamp along the chain from its frame to `map_frame` (or by `pose_topic`),
converted as CDR bodies are, and fused in recorded order in batches
of at most `FUZZYRISK_MAX_SCANS_PER_BATCH`, each durable before the next. A message that cannot be
placed or used is skipped and counted in `skipped` by reason. The body is bounded by
`FUZZYRISK_MAX_BODY_BYTES`, each scan by `FUZZYRISK_MAX_RAYS_PER_SCAN`.
"""


class BagImportResult(BaseModel):
    """What an imported bag did to the map."""

    messages: int = Field(description="scan messages on the topics read")
    scans_fused: int
    skipped: dict[str, int] = Field(description="scan messages left out, by reason")
    rays: int
    cells_updated: int
    batches: int
    version: int = Field(description="the map's version after the last batch")
    topics: dict[str, str] = Field(description="the topics read, with their message types")


_BODY: dict[str, Any] = {"requestBody": {"required": True, "content": {
    media: {"schema": {"type": "string", "format": "binary"}} for media in (*BAG_TYPES, SNIFFED)}}}


def _container(media: str, body: bytes) -> str:
    """The suffix rosbags reads the body by, from its Content-Type and its first bytes."""
    if media == SNIFFED:
        for magic, suffix in BAG_TYPES.values():
            if body.startswith(magic):
                return suffix
        raise Invalid("body: neither a ROS 1 .bag nor an .mcap file (it starts as neither)")
    magic, suffix = BAG_TYPES[media]
    if not body.startswith(magic):
        raise Invalid(f"body: not a {suffix} file (it does not start as one); check the file and its Content-Type")
    return suffix


def _read(body: bytes, suffix: str, options: import_bag.BagOptions, dims: int, limits: Limits,
          max_bytes: int) -> import_bag.BagRead:
    """The bag's scans, read from a temporary file (rosbags reads files), which is removed at once; 413 when
    its chunks would decompress to more than ``max_bytes`` (``FUZZYRISK_MAX_BAG_BYTES``)."""
    handle, name = tempfile.mkstemp(suffix=suffix, prefix="fuzzyrisk-bag-")
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(body)
        declared = bagsize.decompressed_bytes(Path(name))
        if declared > max_bytes:
            raise TooLarge(f"body: the bag's chunks decompress to {declared:,} bytes, more than "
                           f"FUZZYRISK_MAX_BAG_BYTES ({max_bytes:,}): split the bag (ros2 bag convert, rosbags-convert)")
        return import_bag.read_bag(Path(name), options, dims=dims, limits=limits)
    except ServiceError:
        raise
    except bagsize.BagSizeUnknown as exc:
        raise Invalid(f"body: not a readable bag ({exc})") from None
    except import_bag.BagUnreadable as exc:
        raise Invalid(f"body: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - a damaged or hostile file
        # rosbags is not hardened against hostile files: a mutated bag raises KeyError, AssertionError,
        # UnicodeDecodeError, MemoryError (a length field read as a size)...: the body's fault, not ours
        LOG.warning("an uploaded bag could not be read", exc_info=True)
        raise Invalid(f"body: not a readable bag ({type(exc).__name__}: {str(exc)[:200]})") from None
    finally:
        os.unlink(name)


@router.post(
    "/{name}/bags",
    openapi_extra=_BODY,
    description=_DOC,
    responses={415: {"description": "a Content-Type other than application/x-rosbag, application/x-mcap or "
                                    "application/octet-stream"}},
)
async def post_bag(
    name: MapNamePath,
    request: Request,
    service: ServiceDep,
    map_frame: Annotated[str, Query(min_length=1, max_length=256)] = "map",
    topic: Annotated[list[str] | None, Query(description="a topic to read (repeat; default: every LaserScan "
                                                               "and PointCloud2 topic)")] = None,
    pose_topic: Annotated[str | None, Query(description="a PoseStamped, PoseWithCovarianceStamped or Odometry "
                                                        "topic that places its frame instead of /tf")] = None,
    pose_frame: Annotated[str, Query(min_length=1, max_length=256, description="the frame a PoseStamped "
                                     "pose_topic places")] = "base_link",
    range_max: Annotated[float, Query(gt=0, le=1e4, description="a PointCloud2's range, metres")] = (
        import_bag.DEFAULT_CLOUD_RANGE_MAX_M),
) -> BagImportResult:
    """Import a recorded bag's scans into the map."""
    service.admit_batch(name)
    dims = service.get_map(name).dimensions
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media not in BAG_TYPES and media != SNIFFED:
        raise UnsupportedMediaType(f"Content-Type {media!r} is not a bag: send a ROS 1 .bag as application/x-rosbag "
                                   "or a rosbag2 .mcap file as application/x-mcap (application/octet-stream: "
                                   "told by its first bytes)")
    body = await request.body()
    suffix = _container(media, body)
    settings = request.app.state.settings
    limits = Limits(max_scans=settings.max_scans_per_batch, max_rays=settings.max_rays_per_scan)
    options = import_bag.BagOptions(map_frame=map_frame, topics=tuple(topic or ()), pose_topic=pose_topic,
                                    pose_frame=pose_frame, cloud_range_max=range_max)
    read = await run_in_threadpool(_read, body, suffix, options, dims, limits, settings.max_bag_bytes)
    scans = [s.scan for s in read.scans]
    version, rays, cells, batches = service.get_map(name).version, 0, 0, 0
    for i in range(0, len(scans), limits.max_scans):
        result = await service.add_parsed_scans(name, scans[i:i + limits.max_scans])
        version, rays, cells, batches = result.version, rays + result.rays, cells + result.cells_updated, batches + 1
    return BagImportResult(messages=read.messages, scans_fused=len(scans), skipped=dict(Counter(read.skipped)),
                           rays=rays, cells_updated=cells, batches=batches, version=version, topics=read.topics)
