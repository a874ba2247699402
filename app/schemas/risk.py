"""Reads of a map's risk: at points, as a grid, and as a ``nav_msgs/OccupancyGrid``."""

from __future__ import annotations

import math
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, FiniteFloat

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


def parse_corner(text: str) -> tuple[float, ...]:
    """A window's corner as a query writes it, ``x,y`` or ``x,y,z`` (metres), as numbers."""
    parts = text.split(",")
    if len(parts) not in (2, 3):
        raise ValueError(f"must be x,y or x,y,z (metres, comma-separated), got {len(parts)} value(s)")
    try:
        values = tuple(float(part) for part in parts)
    except ValueError:
        raise ValueError(f"must be numbers x,y or x,y,z (metres, comma-separated), got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"must be finite numbers, got {text!r}")
    return values


#: ``x,y`` or ``x,y,z`` in a query, read as a tuple of finite metres
WindowCorner = Annotated[str, AfterValidator(parse_corner)]


class GridWindow(BaseModel):
    """The part of a map a grid read covers: the cells that meet the box ``[min, max]`` (metres), cut to the map
    (a fixed map's box, a growing map's bounds); a corner left out is the map's own edge."""

    model_config = ConfigDict(frozen=True)

    min: tuple[FiniteFloat, ...] | None = None
    max: tuple[FiniteFloat, ...] | None = None

    @property
    def whole(self) -> bool:
        """Whether no corner is given: the read covers the whole map."""
        return self.min is None and self.max is None

    def variant(self) -> dict[str, object]:
        """What the window adds to an ETag's variant (nothing for the whole map: its tags are as before windows)."""
        return {} if self.whole else {"min": self.min, "max": self.max}


#: The whole map: a read with no window.
WHOLE_MAP = GridWindow()


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
