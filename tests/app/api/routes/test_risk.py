"""Grid reads of a window of a map (``?min=x,y[,z]&max=x,y[,z]``) and the place of every grid answer
(``X-Map-Origin``, ``X-Map-Shape``): each format windowed is the slice of the whole map's answer."""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import yaml
from fastapi.testclient import TestClient
from mcap.reader import make_reader
from PIL import Image
from rosbags.typesys import Stores, get_typestore

from app.api.factory import create_app
from app.config import Settings
from tests.conftest import error_message

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
GRID_TYPE = "nav_msgs/msg/OccupancyGrid"
#: lab: origin (-5, -5), 0.1 m cells, 100 x 100. Corners inside cells, so the cells they fall in are plain.
WINDOW = {"min": "-1.23,0.47", "max": "3.74,3.05"}
WINDOW_CELLS = (slice(37, 88), slice(54, 81))  # floor((min + 5) / 0.1) .. floor((max + 5) / 0.1) + 1
#: A window reaching past the map's low corner: cut to the map's box.
CLIPPED = {"min": "-20,-20", "max": "-3.96,-2.03"}
CLIPPED_CELLS = (slice(0, 11), slice(0, 30))


def laser(x: float, y: float, theta: float, wall: float) -> dict[str, Any]:
    """A LaserScan of 90 beams over +-45 degrees facing a straight wall ``wall`` ahead."""
    angles = -math.pi / 4 + (math.pi / 2) / 89 * np.arange(90)
    return {"pose": {"x": x, "y": y, "theta": theta}, "angle_min": -math.pi / 4, "angle_increment": math.pi / 2 / 89,
            "ranges": (wall / np.cos(angles)).round(6).tolist(), "range_min": 0.1, "range_max": 20.0}


LASERS = [laser(0.0, 0.0, 0.0, 3.05), laser(-2.0, -3.0, math.pi / 2, 6.05), laser(-3.5, -3.0, math.pi, 1.2)]


@pytest.fixture(scope="module")
def maps(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """A service holding ``lab`` (2-D: origin (-5, -5), 0.1 m cells, 100 x 100) with three LaserScans fused, and
    ``hall`` (3-D: origin (-4, -4, 0), 0.2 m cells, 40 x 40 x 15) with a wall at x = 2.5 seen from z = 1. The
    tests that use it only read."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("windows"), plan_warmup=False, plan_workers=1,
                        disk_reserve_bytes=64 * 1024)
    with TestClient(create_app(settings)) as client:
        assert client.post("/maps", json={"name": "lab", "resolution": 0.1, "origin": [-5.0, -5.0],
                                          "size": [10.0, 10.0]}).status_code == 201
        assert client.post("/maps/lab/scans", json={"scans": LASERS}).status_code == 200
        assert client.post("/maps", json={"name": "hall", "resolution": 0.2, "origin": [-4.0, -4.0, 0.0],
                                          "size": [8.0, 8.0, 3.0]}).status_code == 201
        points = np.column_stack([np.full(300, 2.5), np.linspace(-1.5, 1.5, 300), np.tile([-0.6, 0.0, 0.4], 100)])
        cloud = {"pose": {"position": [0.0, 0.0, 1.0], "orientation": [0, 0, 0, 1]}, "points": points.tolist(),
                 "range_max": 10.0}
        assert client.post("/maps/hall/scans", json={"scans": [cloud]}).status_code == 200
        yield client


@pytest.fixture
def scanned(maps: TestClient) -> TestClient:
    return maps


@pytest.fixture
def hall(maps: TestClient) -> TestClient:
    return maps


def get(client: TestClient, path: str, **params: Any) -> Any:
    response = client.get(path, params=params)
    assert response.status_code == 200, response.text
    return response


def place(response: Any) -> tuple[list[float], tuple[int, ...]]:
    """``X-Map-Origin`` and ``X-Map-Shape`` of an answer."""
    origin = [float(v) for v in response.headers["X-Map-Origin"].split(",")]
    return origin, tuple(int(n) for n in response.headers["X-Map-Shape"].split(","))


def npy_of(response: Any) -> np.ndarray:
    return np.load(io.BytesIO(response.content), allow_pickle=False)


def corner(origin: list[float], cells: tuple[slice, ...], resolution: float) -> list[float]:
    return [o + s.start * resolution for o, s in zip(origin, cells)]


def plane(cells: tuple[slice, ...]) -> tuple[slice, slice]:
    """Rows along y, columns along x: how an OccupancyGrid's data and an image hold cells."""
    return cells[1], cells[0]


# ---------------------------------------------------------------- every format, windowed = the slice


@pytest.mark.parametrize(("window", "cells"), [(WINDOW, WINDOW_CELLS), (CLIPPED, CLIPPED_CELLS)])
@pytest.mark.parametrize("layer", ["risk", "observed"])
def test_a_windowed_npy_is_the_slice_of_the_whole_one_bit_for_bit(scanned: TestClient, window: dict, cells: tuple,
                                                                  layer: str) -> None:
    whole = npy_of(get(scanned, "/maps/lab/risk.npy", layer=layer))
    response = get(scanned, "/maps/lab/risk.npy", layer=layer, **window)
    part = npy_of(response)
    expected = whole[cells]
    assert part.dtype == whole.dtype and part.shape == expected.shape
    assert part.tobytes() == expected.tobytes()
    assert np.unique(expected).size > 1  # the window holds cells of more than one value: the slice is no accident
    origin, shape = place(response)
    assert shape == part.shape
    assert origin == pytest.approx(corner([-5.0, -5.0], cells, 0.1), abs=1e-12)


@pytest.mark.parametrize(("window", "cells"), [(WINDOW, WINDOW_CELLS), (CLIPPED, CLIPPED_CELLS)])
def test_a_windowed_json_grid_is_the_slice_and_states_its_origin_and_shape(scanned: TestClient, window: dict,
                                                                          cells: tuple) -> None:
    whole = get(scanned, "/maps/lab/risk").json()
    part = get(scanned, "/maps/lab/risk", **window).json()
    assert part["risk"] == np.asarray(whole["risk"])[cells].tolist()
    assert part["observed"] == np.asarray(whole["observed"])[cells].tolist()
    assert part["shape"] == [cells[0].stop - cells[0].start, cells[1].stop - cells[1].start]
    assert part["origin"] == pytest.approx(corner(whole["origin"], cells, 0.1), abs=1e-12)
    assert (part["resolution"], part["version"], part["frame_id"]) == (0.1, 1, "map")


@pytest.mark.parametrize(("window", "cells"), [(WINDOW, WINDOW_CELLS), (CLIPPED, CLIPPED_CELLS)])
def test_a_windowed_png_is_the_crop_of_the_whole_picture(scanned: TestClient, window: dict, cells: tuple) -> None:
    whole = np.asarray(Image.open(io.BytesIO(get(scanned, "/maps/lab/risk.png").content)))
    response = get(scanned, "/maps/lab/risk.png", **window)
    part = np.asarray(Image.open(io.BytesIO(response.content)))
    rows, columns = plane(cells)
    ny = whole.shape[0]  # the top row is the highest y
    assert np.array_equal(part, whole[ny - rows.stop:ny - rows.start, columns])
    _, shape = place(response)
    assert (part.shape[1], part.shape[0]) == shape  # nx pixels a row, ny rows


@pytest.mark.parametrize(("window", "cells"), [(WINDOW, WINDOW_CELLS), (CLIPPED, CLIPPED_CELLS)])
@pytest.mark.parametrize("mode", ["trinary", "probability"])
def test_a_windowed_occupancy_grid_is_the_slice_in_json_cdr_and_mcap(scanned: TestClient, window: dict,
                                                                     cells: tuple, mode: str) -> None:
    whole = get(scanned, "/maps/lab/occupancy_grid", mode=mode).json()
    full = np.asarray(whole["data"], dtype=np.int8).reshape(whole["info"]["height"], whole["info"]["width"])
    expected = full[plane(cells)]
    origin = corner([-5.0, -5.0], cells, 0.1)

    part = get(scanned, "/maps/lab/occupancy_grid", mode=mode, **window).json()
    info = part["info"]
    assert (info["height"], info["width"]) == expected.shape
    assert np.array_equal(np.asarray(part["data"], dtype=np.int8).reshape(expected.shape), expected)
    assert [info["origin"]["position"]["x"], info["origin"]["position"]["y"]] == pytest.approx(origin, abs=1e-12)

    cdr = get(scanned, "/maps/lab/occupancy_grid.cdr", mode=mode, **window).content
    message = TYPESTORE.deserialize_cdr(cdr, GRID_TYPE)
    assert (message.info.height, message.info.width) == expected.shape
    assert message.data.astype(np.int8).tobytes() == expected.tobytes()
    assert [message.info.origin.position.x, message.info.origin.position.y] == pytest.approx(origin, abs=1e-12)

    mcap = get(scanned, "/maps/lab/occupancy_grid.mcap", mode=mode, **window).content
    [(channel, data)] = [(c.topic, m.data) for _, c, m in make_reader(io.BytesIO(mcap)).iter_messages()]
    assert (channel, data) == ("/map", cdr)


def _nav2(archive: bytes) -> tuple[dict[str, Any], np.ndarray]:
    with zipfile.ZipFile(io.BytesIO(archive)) as zipped:
        meta = yaml.safe_load(zipped.read("map.yaml"))
        return meta, np.asarray(Image.open(io.BytesIO(zipped.read(meta["image"]))))


@pytest.mark.parametrize(("window", "cells"), [(WINDOW, WINDOW_CELLS), (CLIPPED, CLIPPED_CELLS)])
def test_a_windowed_nav2_export_is_the_crop_of_the_whole_one_at_its_own_origin(scanned: TestClient, window: dict,
                                                                               cells: tuple) -> None:
    whole_meta, whole = _nav2(get(scanned, "/maps/lab/export/nav2").content)
    meta, part = _nav2(get(scanned, "/maps/lab/export/nav2", **window).content)
    rows, columns = plane(cells)
    ny = whole.shape[0]
    assert np.array_equal(part, whole[ny - rows.stop:ny - rows.start, columns])
    assert meta["origin"] == pytest.approx([*corner(whole_meta["origin"][:2], cells, 0.1), 0.0], abs=1e-12)
    assert {k: v for k, v in meta.items() if k != "origin"} == {k: v for k, v in whole_meta.items() if k != "origin"}


def test_a_windowed_recording_holds_the_windowed_grid_and_every_scan(scanned: TestClient) -> None:
    def messages(data: bytes) -> tuple[list[bytes], list[tuple[str, int, bytes]]]:
        read = [(c.topic, m.sequence, m.data) for _, c, m in make_reader(io.BytesIO(data)).iter_messages()]
        return [d for topic, _, d in read if topic == "/map"], sorted(m for m in read if m[0] != "/map")

    whole_map, whole_scans = messages(get(scanned, "/maps/lab/export/mcap").content)
    part_map, part_scans = messages(get(scanned, "/maps/lab/export/mcap", **WINDOW).content)
    assert part_map == [get(scanned, "/maps/lab/occupancy_grid.cdr", **WINDOW).content] != whole_map
    assert part_scans == whole_scans and len(part_scans) == 2 * len(LASERS)  # each LaserScan with its transform


# ---------------------------------------------------------------- 3-D


def test_a_3d_window_is_the_slice_of_the_3d_grid(hall: TestClient) -> None:
    window = {"min": "1.1,-0.9,0.5", "max": "3.3,1.3,1.7"}  # origin (-4, -4, 0), 0.2 m cells
    cells = (slice(25, 37), slice(15, 27), slice(2, 9))
    whole = npy_of(get(hall, "/maps/hall/risk.npy"))
    response = get(hall, "/maps/hall/risk.npy", **window)
    part = npy_of(response)
    assert part.tobytes() == whole[cells].tobytes() and part.shape == (12, 12, 7)
    assert np.unique(part).size > 1
    origin, shape = place(response)
    assert shape == (12, 12, 7)
    assert origin == pytest.approx(corner([-4.0, -4.0, 0.0], cells, 0.2), abs=1e-12)
    as_json = get(hall, "/maps/hall/risk", **window).json()
    assert as_json["risk"] == np.asarray(get(hall, "/maps/hall/risk").json()["risk"])[cells].tolist()
    assert as_json["shape"] == [12, 12, 7]


def test_a_3d_map_windowed_in_the_plane_projects_to_the_slice_of_its_projection(hall: TestClient) -> None:
    window = {"min": "1.1,-0.9,-10", "max": "3.3,1.3,10"}  # every height: the columns are whole
    cells = (slice(25, 37), slice(15, 27))
    whole = get(hall, "/maps/hall/occupancy_grid").json()
    full = np.asarray(whole["data"]).reshape(40, 40)
    part = get(hall, "/maps/hall/occupancy_grid", **window).json()
    assert np.array_equal(np.asarray(part["data"]).reshape(12, 12), full[plane(cells)])
    assert (np.asarray(part["data"]) == 100).any()


# ---------------------------------------------------------------- the place of every answer


@pytest.mark.parametrize(("path", "params"), [
    ("/maps/lab/risk.npy", {}), ("/maps/lab/risk.npy", {"layer": "observed"}), ("/maps/lab/risk.png", {"scale": 3}),
    ("/maps/lab/risk", {"format": "npy"}), ("/maps/lab/risk", {"format": "png"}), ("/maps/lab/risk", {}),
    ("/maps/lab/occupancy_grid.cdr", {}), ("/maps/lab/export/nav2", {}), ("/maps/lab/export/mcap", {}),
])
def test_every_grid_answer_of_a_fixed_map_says_its_origin_and_shape(scanned: TestClient, path: str,
                                                                   params: dict) -> None:
    response = get(scanned, path, **params)
    assert (response.headers["X-Map-Origin"], response.headers["X-Map-Shape"]) == ("-5.0,-5.0", "100,100")
    windowed = get(scanned, path, **params, **WINDOW)
    assert (windowed.headers["X-Map-Origin"], windowed.headers["X-Map-Shape"]) == ("-1.3,0.4", "51,27")


def test_a_3d_maps_npy_says_its_origin_and_shape_in_the_arrays_order(hall: TestClient) -> None:
    response = get(hall, "/maps/hall/risk.npy")
    assert (response.headers["X-Map-Origin"], response.headers["X-Map-Shape"]) == ("-4.0,-4.0,0.0", "40,40,15")
    assert npy_of(response).shape == (40, 40, 15)


def test_the_openapi_document_declares_the_window_and_the_place_headers(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    for path in ("/maps/{name}/risk", "/maps/{name}/risk.npy", "/maps/{name}/risk.png", "/maps/{name}/occupancy_grid",
                 "/maps/{name}/occupancy_grid.{encoding}", "/maps/{name}/export/nav2", "/maps/{name}/export/mcap"):
        operation = paths[path]["get"]
        query = {p["name"] for p in operation["parameters"] if p["in"] == "query"}
        assert {"min", "max"} <= query, path
        assert {"X-Map-Origin", "X-Map-Shape"} <= set(operation["responses"]["200"]["headers"]), path


# ---------------------------------------------------------------- refusals


@pytest.mark.parametrize(("params", "field", "needle"), [
    ({"min": "1,2,3"}, "min", "3 coordinates"),
    ({"max": "1,2,3"}, "max", "3 coordinates"),
    ({"min": "1"}, "min", "x,y or x,y,z"),
    ({"max": "1,2,3,4"}, "max", "x,y or x,y,z"),
    ({"min": "a,b"}, "min", "numbers"),
    ({"max": "1,,2"}, "max", "numbers"),
    ({"min": "nan,0"}, "min", "finite"),
    ({"max": "0,inf"}, "max", "finite"),
    ({"min": "1e999,0"}, "min", "finite"),
    ({"min": "20,20"}, "min", "meets no cell"),
    ({"max": "-6,0"}, "max", "meets no cell"),
    ({"min": "1,1", "max": "0,2"}, "min", "exceeds max"),
])
@pytest.mark.parametrize("path", ["/maps/lab/risk", "/maps/lab/risk.npy", "/maps/lab/risk.png",
                                  "/maps/lab/occupancy_grid", "/maps/lab/occupancy_grid.cdr",
                                  "/maps/lab/export/nav2", "/maps/lab/export/mcap"])
def test_a_bad_window_answers_422_naming_min_or_max(scanned: TestClient, path: str, params: dict, field: str,
                                                    needle: str) -> None:
    response = scanned.get(path, params=params)
    assert response.status_code == 422, response.text
    message = error_message(response)
    assert field in message and needle in message, message


def test_a_window_of_the_wrong_dimension_on_a_3d_map_is_refused(hall: TestClient) -> None:
    response = hall.get("/maps/hall/risk.npy", params={"max": "1,1"})
    assert response.status_code == 422 and "max has 2 coordinates; this map is 3-D" in error_message(response)


def test_a_window_of_a_map_too_big_for_json_can_be_read_as_json(client: TestClient, kit: Any) -> None:
    big = {**kit.MAP_2D, "name": "big", "size": [210.0, 200.0]}  # 2100 x 2000 cells, above the 4 M of JSON
    assert client.post("/maps", json=big).status_code == 201
    assert client.get("/maps/big/risk").status_code == 422
    part = get(client, "/maps/big/risk", min="-1,-1", max="1,1").json()
    assert part["shape"] == [21, 21] and {v for row in part["risk"] for v in row} == {0.5}


# ---------------------------------------------------------------- ETags


@pytest.mark.parametrize("path", ["/maps/lab/risk", "/maps/lab/risk.npy", "/maps/lab/risk.png",
                                  "/maps/lab/occupancy_grid", "/maps/lab/occupancy_grid.mcap",
                                  "/maps/lab/export/nav2", "/maps/lab/export/mcap"])
def test_each_window_has_its_own_etag_and_a_304_holds_for_the_same_window(lab: TestClient, kit: Any,
                                                                          path: str) -> None:
    assert lab.post("/maps/lab/scans", json={"scans": LASERS}).status_code == 200
    tags = {get(lab, path, **params).headers["ETag"] for params in ({}, WINDOW, CLIPPED, {"min": WINDOW["min"]})}
    assert len(tags) == 4
    tag = get(lab, path, **WINDOW).headers["ETag"]
    again = lab.get(path, params=WINDOW, headers={"If-None-Match": tag})
    assert again.status_code == 304 and again.content == b"" and again.headers["ETag"] == tag
    other = lab.get(path, params=CLIPPED, headers={"If-None-Match": tag})
    assert other.status_code == 200 and other.headers["ETag"] != tag
    assert lab.post("/maps/lab/scans", json={"scans": [kit.laser(wall=2.0)]}).status_code == 200
    assert lab.get(path, params=WINDOW, headers={"If-None-Match": tag}).status_code == 200  # a new version
