"""A map's trajectory out: the sensor pose of every stored scan, with its stamp, as a ``nav_msgs/Path``."""

from __future__ import annotations

from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field

from app.schemas.common import PathMessage, PoseMsg, StampIn


class Trajectory(PathMessage):
    """The sensor poses the map's stored scans were posted with, in the order they were fused: a ``nav_msgs/Path``
    (``header`` and ``poses``, shaped as a plan's answer) with what the map says of it.

    ``header.stamp`` is when the map reached this version (its last batch's commit), as an OccupancyGrid read
    stamps it. One pose per stored scan; its header's stamp is the scan's (its ``header.stamp``, its message's, or
    when the service received it), 0 for a scan stored before scans kept stamps (see ``unstamped``). A LaserScan's
    pose as posted (2-D maps: z 0, its theta as a yaw quaternion); a point cloud's sensor origin with the identity
    orientation (a cloud is stored in the map frame, with its origin only).
    """

    version: int = Field(description="the map version the poses are of")
    from_version: int = Field(
        description="the version the map's history starts after (its base snapshot's, as GET /maps/{name} shows "
        "history.from_version): the scans of every batch after it are listed; those folded into the base are not")
    unstamped: int = Field(description="poses stamped 0 because their scan was stored without a stamp")


class _HeaderIn(BaseModel):
    model_config = ConfigDict(extra="ignore")

    stamp: StampIn
    frame_id: str


class _PoseStampedIn(BaseModel):
    header: _HeaderIn
    pose: PoseMsg


class CorrectedPath(BaseModel):
    """A corrected trajectory (``PUT /maps/{name}/trajectory``): a ``nav_msgs/Path`` as a SLAM node publishes it, in
    JSON as ``GET /maps/{name}/trajectory`` gives one.

    ``header.frame_id`` is the map's frame; each pose's stamp is Unix time (``{"sec", "nanosec"}``, integers), the
    stamps strictly increasing; orientations are unit quaternions ``[x, y, z, w]``. A pose's own ``frame_id`` is
    not read (the path's applies, as in nav_msgs).
    """

    header: _HeaderIn = Field(description="frame_id: the map's frame")
    poses: list[_PoseStampedIn] = Field(min_length=1, description="the sensor's (or, with the offset query, the "
                                        "robot's) poses, stamps strictly increasing")


class RebuildState(StrEnum):
    """Where a map's rebuild at a corrected trajectory stands."""

    NONE = "none"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


class RebuildStatus(BaseModel):
    """The map's latest rebuild at a corrected trajectory (``GET /maps/{name}/rebuild``)."""

    state: RebuildState = Field(description="none (never corrected), running, done, or failed (error says why)")
    id: str | None = Field(None, description="the correction's id, as its PUT answered it")
    requested: str | None = Field(None, description="when the correction was acknowledged (ISO 8601, UTC)")
    from_version: int | None = Field(
        None, description="the map's version when the correction was acknowledged: the scans stored up to it take "
        "their corrected poses, later ones keep theirs")
    scans_reposed: int = Field(0, description="stored scans given a new pose")
    scans_done: int = Field(0, description="scans of the map's history fused again so far")
    scans_total: int = Field(0, description="scans of the map's history to fuse again")
    elapsed_s: float = Field(0.0, description="seconds since the rebuild started (its whole time once finished)")
    eta_s: float | None = Field(None, description="seconds left, estimated from the rate so far (running only)")
    version: int | None = Field(None, description="the map's version once the rebuilt map replaced it (done)")
    error: str | None = Field(None, description="why it failed (failed)")


class RebuildAccepted(BaseModel):
    """``PUT /maps/{name}/trajectory``'s answer: the correction is stored, the rebuild under way."""

    rebuild: RebuildStatus
