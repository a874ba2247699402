"""Reads of a map's risk: at points, as a grid, and as a ``nav_msgs/OccupancyGrid``."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

from app.schemas.common import Header, PoseMsg, Time, Vector


class RiskQuery(BaseModel):
    """World points [x, y(, z)] inside the map."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"points": [[1.0, 0.0], [2.99, 0.0]]}]})

    points: Annotated[list[Vector], Field(min_length=1)]


class RiskValues(BaseModel):
    risk: list[float]
    version: int


class RiskGridJSON(BaseModel):
    """The risk grid, indexed ``risk[i][j](k)`` along x, y(, z); cell centre = origin + (index + 0.5) * resolution."""

    name: str
    version: int
    frame_id: str = Field(description="the map's ROS frame, in which origin is given")
    resolution: float
    origin: list[float]
    shape: list[int]
    risk: list[Any] = Field(description="float in [0, 1], rounded to 1e-6 (format=npy for exact float32)")
    observed: list[Any] = Field(description="false where no beam ever reached the cell (unknown)")


class MapMetaData(BaseModel):
    map_load_time: Time
    resolution: float
    width: int
    height: int
    origin: PoseMsg


class OccupancyGridMessage(BaseModel):
    """``nav_msgs/OccupancyGrid`` as JSON (rosbridge's shape): ``data[j * width + i]`` for cell (i, j) from the
    origin, 0..100 occupancy, -1 unknown."""

    header: Header
    info: MapMetaData
    data: list[int]


class OccupancyGrid(OccupancyGridMessage):
    """``nav_msgs/OccupancyGrid``: ``data[j * width + i]`` for cell (i, j) from the origin, -1 unknown.

    ``header.stamp`` and ``info.map_load_time`` are the time of the map's last batch (its creation
    before one): every read of one version is the same document. ``version`` is not a message field.
    """

    version: int = Field(description="the map version (not part of the ROS message: drop it before publishing)")
