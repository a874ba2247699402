"""A map's trajectory out: the sensor pose of every stored scan, with its stamp, as a ``nav_msgs/Path``."""

from __future__ import annotations

from pydantic import Field

from app.schemas.common import PathMessage


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
