"""A nav_msgs/OccupancyGrid in (JSON and CDR) as a saved map: its cells, its geometry, and what is refused."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from fastapi.exceptions import RequestValidationError

from app.errors import Invalid, TooLarge
from app.ros import grid_in, messages_out
from app.ros.msgtypes import typestore
from tests.app._ros import cdr, laser_msg, store, wall_ranges

#: A 3 x 2 grid: row j = 0 is [free, occupied, unknown], row j = 1 is [50, 0, 100].
DATA = [0, 100, -1, 50, 0, 100]


def grid_json(data: list[int] = DATA, *, width: int = 3, height: int = 2, yaw: float = 0.0,
              **info: Any) -> dict[str, Any]:
    """An OccupancyGrid as the service's JSON read gives it (``version`` included)."""
    return {
        "header": {"stamp": {"sec": 5, "nanosec": 0}, "frame_id": "robot1/map"},
        "info": {"map_load_time": {"sec": 5, "nanosec": 0}, "resolution": info.pop("resolution", 0.1),
                 "width": width, "height": height,
                 "origin": {"position": {"x": -1.5, "y": 2.0, "z": 0.0},
                            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}},
                 **info},
        "data": data, "version": 7,
    }


def grid_cdr(data: list[int] = DATA, *, width: int = 3, height: int = 2, frame_id: str = "robot1/map") -> bytes:
    message = messages_out.occupancy_grid_message(np.asarray(data), width=width, height=height, resolution=0.1,
                                                  origin_xy=(-1.5, 2.0), frame_id=frame_id,
                                                  stamp={"sec": 5, "nanosec": 0})
    return messages_out.occupancy_grid_cdr(message)


def occupancy(saved: Any) -> np.ndarray:
    cells = saved.cells()
    return cells.occupancy[cells.codes]


@pytest.mark.parametrize("encoding", ["json", "cdr"])
def test_a_grid_becomes_its_geometry_and_cells_indexed_along_x_then_y(encoding: str) -> None:
    saved = (grid_in.open_json(json.dumps(grid_json()).encode(), max_cells=100) if encoding == "json"
             else grid_in.open_cdr(grid_cdr(), max_cells=100))
    assert (saved.resolution, saved.origin, saved.width, saved.height, saved.frame_id) == \
        (pytest.approx(0.1), (-1.5, 2.0), 3, 2, "robot1/map")
    p = occupancy(saved)
    assert p.shape == (3, 2)
    assert p[:, 0].tolist()[:2] == [0.0, 1.0] and math.isnan(p[2, 0])
    assert p[:, 1].tolist() == [0.5, 0.0, 1.0]


def test_a_json_grid_and_its_cdr_read_alike() -> None:
    rng = np.random.default_rng(5)
    data = rng.integers(-1, 101, 40 * 30).tolist()
    from_json = grid_in.open_json(json.dumps(grid_json(data, width=40, height=30)).encode(), max_cells=10_000)
    from_cdr = grid_in.open_cdr(grid_cdr(data, width=40, height=30), max_cells=10_000)
    assert np.array_equal(occupancy(from_json), occupancy(from_cdr), equal_nan=True)
    assert np.array_equal(np.nan_to_num(occupancy(from_json).T.reshape(-1) * 100, nan=-1).round(), data)


def test_a_frame_id_left_empty_is_none() -> None:
    assert grid_in.open_cdr(grid_cdr(frame_id=""), max_cells=100).frame_id is None


@pytest.mark.parametrize(("change", "says"), [
    ({"yaw": 0.3}, "info.origin.orientation is a rotation of 0.3 rad"),
    ({"resolution": 0.0}, "info.resolution must be a positive number"),
    ({"data": [0, 100, -1, 50, 0, 101]}, "data[5] is 101"),
    ({"data": [0, -2, -1, 50, 0, 100]}, "data[1] is -2"),
    ({"data": [0, 100, -1]}, "data holds 3 values, not info.width x info.height = 3 x 2 = 6"),
    ({"width": 0, "data": []}, "the map is 0 x 2 cells"),
])
def test_a_grid_the_service_cannot_start_from_is_refused_naming_the_field(change: dict[str, Any], says: str) -> None:
    body = grid_json(**change)
    with pytest.raises(Invalid) as refused:
        grid_in.open_json(json.dumps(body).encode(), max_cells=100).cells()
    assert says in refused.value.message


def test_float_noise_in_an_unrotated_origin_is_no_rotation_and_a_zero_quaternion_is_refused() -> None:
    body = grid_json()
    body["info"]["origin"]["orientation"] = {"x": 0.0, "y": 0.0, "z": 1e-13, "w": 1.0}
    assert grid_in.open_json(json.dumps(body).encode(), max_cells=100).width == 3
    body["info"]["origin"]["orientation"] = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}
    with pytest.raises(Invalid, match="unit quaternion"):
        grid_in.open_json(json.dumps(body).encode(), max_cells=100)


def test_a_grid_over_the_cell_limit_is_refused_before_its_data_is_read() -> None:
    with pytest.raises(TooLarge, match=r"3 x 2 = 6 cells, more than FUZZYRISK_MAX_MAP_CELLS \(5\)"):
        grid_in.open_cdr(grid_cdr(), max_cells=5)


def test_what_is_not_an_occupancy_grid_is_refused() -> None:
    with pytest.raises(RequestValidationError) as refused:
        grid_in.open_json(b'{"header": {}, "data": [1, 2]}', max_cells=100)
    assert {tuple(e["loc"][:2]) for e in refused.value.errors()} >= {("body", "info"), ("body", "header")}
    with pytest.raises(Invalid, match="not a CDR-serialized nav_msgs/msg/OccupancyGrid"):
        grid_in.open_cdr(b"\x00\x01\x00\x00 not a grid", max_cells=100)
    ts = store("jazzy")
    scan = cdr(ts, laser_msg(ts, wall_ranges()))  # a genuine message of another type
    with pytest.raises(Invalid, match="not a CDR-serialized nav_msgs/msg/OccupancyGrid"):
        grid_in.open_cdr(scan, max_cells=100_000)


def test_a_big_endian_grid_reads_as_a_little_endian_one() -> None:
    ts = typestore()
    message = ts.deserialize_cdr(grid_cdr(), messages_out.OCCUPANCY_GRID)
    big = cdr(ts, message, little_endian=False)
    assert big != grid_cdr()
    assert np.array_equal(occupancy(grid_in.open_cdr(big, max_cells=100)),
                          occupancy(grid_in.open_cdr(grid_cdr(), max_cells=100)), equal_nan=True)
