"""A ``nav_msgs/OccupancyGrid`` in, as a saved map to start a map from: JSON (the service's own OccupancyGrid read,
or rosbridge's shape) or CDR (the bytes of ``serialize_message``, as ``occupancy_grid.cdr`` answers).

``data[j * width + i]`` is cell (i, j): 0..100 its occupancy in percent (0 free, 100 occupied),
-1 unknown; any other value is refused, as is a grid whose origin is rotated (this service's grids
are aligned with their frame).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from app.errors import Invalid
from app.formats.saved_maps import MapCells, SavedMap, check_geometry
from app.ros.messages_in import decode
from app.ros.messages_out import OCCUPANCY_GRID
from app.schemas import OccupancyGridMessage
from app.schemas.common import located_errors

#: The rotation an origin's quaternion may hold and still count as none (float noise of a yaw of 0), radians.
_MAX_ROTATION_RAD = 1e-9
#: An OccupancyGrid value's code is value + 1: 0 unknown, 1 .. 101 occupancy 0 .. 100 percent.
_OCCUPANCY = np.concatenate([[np.nan], np.arange(101) / 100.0])


def open_json(body: bytes, *, max_cells: int) -> SavedMap:
    """The grid of a JSON ``OccupancyGridMessage`` (extra fields, such as the read's ``version``, are ignored)."""
    try:
        msg = OccupancyGridMessage.model_validate_json(body)
    except ValidationError as exc:
        # the whole input of a bad message is its data: never echoed
        raise RequestValidationError(located_errors(exc, ("body",), hidden=(dict, list, str, bytes))) from None
    info, origin = msg.info, msg.info.origin
    return _saved(width=info.width, height=info.height, resolution=info.resolution,
                  position=(origin.position.x, origin.position.y),
                  orientation=(origin.orientation.x, origin.orientation.y, origin.orientation.z, origin.orientation.w),
                  frame_id=msg.header.frame_id, size=len(msg.data),
                  data=lambda: np.asarray(msg.data, dtype=np.int64), max_cells=max_cells)


def open_cdr(body: bytes, *, max_cells: int) -> SavedMap:
    """The grid of a CDR-serialized ``nav_msgs/msg/OccupancyGrid``."""
    msg = decode(body, OCCUPANCY_GRID)
    info, origin = msg.info, msg.info.origin
    return _saved(width=int(info.width), height=int(info.height), resolution=float(info.resolution),
                  position=(float(origin.position.x), float(origin.position.y)),
                  orientation=(float(origin.orientation.x), float(origin.orientation.y),
                               float(origin.orientation.z), float(origin.orientation.w)),
                  frame_id=str(msg.header.frame_id), size=len(msg.data),
                  data=lambda: np.asarray(msg.data).astype(np.int64), max_cells=max_cells)


def _saved(*, width: int, height: int, resolution: float, position: tuple[float, float],
           orientation: tuple[float, float, float, float], frame_id: str, size: int,
           data: Callable[[], np.ndarray], max_cells: int) -> SavedMap:
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise Invalid(f"body: info.resolution must be a positive number of metres per cell, got {resolution!r}")
    if not all(math.isfinite(v) for v in position):
        raise Invalid(f"body: info.origin.position must be finite, got {list(position)}")
    x, y, z, w = orientation
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(norm) and norm > 0.0):
        raise Invalid(f"body: info.origin.orientation must be a unit quaternion, got {list(orientation)}")
    angle = 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), abs(w))
    if angle > _MAX_ROTATION_RAD:
        raise Invalid(f"body: info.origin.orientation is a rotation of {angle:.6g} rad (yaw "
                      f"{2.0 * math.atan2(z, w):.6g} rad): a rotated grid is not supported (this service's grids are "
                      "aligned with their frame); send the grid with an unrotated origin")
    check_geometry("body", resolution, position, width, height, max_cells)
    if size != width * height:
        raise Invalid(f"body: data holds {size:,} values, not info.width x info.height = {width} x {height} = "
                      f"{width * height:,}")

    def cells() -> MapCells:
        values = data()
        bad = np.flatnonzero((values < -1) | (values > 100))
        if bad.size:
            raise Invalid(f"body: data[{int(bad[0])}] is {int(values[bad[0]])}: an OccupancyGrid value is an "
                          "occupancy 0..100, or -1 for unknown")
        codes = (values + 1).astype(np.uint16).reshape(height, width).T
        return MapCells(codes=np.ascontiguousarray(codes), occupancy=_OCCUPANCY.copy())

    return SavedMap(resolution=resolution, origin=position, width=width, height=height, frame_id=frame_id or None,
                    decode=cells)
