"""The risk grid out: .npy, JSON, PNG, nav_msgs/OccupancyGrid, and Nav2 map_server files read back by a
reader that follows Nav2's map_io.cpp (PGM/PNG + YAML, occ = (255 - p) / 255 for negate 0)."""

from __future__ import annotations

import io
import math
import zipfile
from typing import Any

import numpy as np
import pytest
import yaml
from fastapi.testclient import TestClient
from PIL import Image

from app.exports import NAV2_FREE_THRESH as FREE
from app.exports import UNKNOWN_RGB


@pytest.fixture
def scanned(lab: TestClient, kit: Any) -> TestClient:
    """``lab`` after scans of a wall at x = 3.05 m from two poses, and one scan looking up (+y)."""
    scans = [kit.laser(wall=3.05), kit.laser(y=1.0, wall=3.05), kit.laser(x=-2.0, y=-3.0, theta=math.pi / 2, wall=6.05)]
    assert lab.post("/maps/lab/scans", json={"scans": scans}).status_code == 200
    return lab


def _grid(client: TestClient) -> tuple[np.ndarray, np.ndarray]:
    body = client.get("/maps/lab/risk").json()
    return np.asarray(body["risk"], dtype=np.float64), np.asarray(body["observed"], dtype=bool)


def _cell(x: float, y: float) -> tuple[int, int]:  # lab: origin (-5, -5), 0.1 m cells
    return int(math.floor((x + 5.0) / 0.1)), int(math.floor((y + 5.0) / 0.1))


def test_npy_is_the_float32_grid_indexed_along_x_then_y(scanned: TestClient, kit: Any) -> None:
    response = scanned.get("/maps/lab/risk", params={"format": "npy"})
    assert response.headers["content-type"] == "application/x-npy"
    assert response.headers["x-map-version"] == "1" and response.headers["x-map-origin"] == "-5.0,-5.0"
    risk = np.load(io.BytesIO(response.content), allow_pickle=False)
    assert risk.dtype == np.float32 and risk.shape == (100, 100)
    points = [[3.05, 0.0], [1.0, 0.0], [-2.0, 3.05], [4.9, -4.9]]
    queried = scanned.post("/maps/lab/risk/query", json={"points": points}).json()["risk"]
    assert [float(risk[_cell(*p)]) for p in points] == queried
    assert queried[0] > 0.65 and queried[1] < 0.45 and queried[2] > 0.65 and queried[3] == 0.5


def test_json_grid_matches_the_npy_grid(scanned: TestClient, kit: Any) -> None:
    body = scanned.get("/maps/lab/risk").json()
    assert body["shape"] == [100, 100] and body["resolution"] == 0.1 and body["version"] == 1
    np.testing.assert_allclose(np.asarray(body["risk"]), kit.risk_npy(scanned, "lab"), atol=1e-6)
    observed = np.asarray(body["observed"])
    assert observed[_cell(1.0, 0.0)] and not observed[_cell(4.9, -4.9)]


def test_png_is_one_pixel_a_cell_with_the_highest_y_on_top(scanned: TestClient) -> None:
    risk, observed = _grid(scanned)
    image = np.asarray(Image.open(io.BytesIO(scanned.get("/maps/lab/risk", params={"format": "png"}).content)))
    assert image.shape == (100, 100, 3)
    unknown_pixels = (image == UNKNOWN_RGB).all(axis=2)
    # pixel (row, col) shows cell (i = col, j = height - 1 - row): unknown exactly where never observed
    assert np.array_equal(unknown_pixels, (~observed).T[::-1])
    row, col = 99 - _cell(-2.0, 2.95)[1], _cell(-2.0, 2.95)[0]  # the wall seen looking up: upper half
    assert row < 50 and not unknown_pixels[row, col]


def test_png_colours_get_darker_with_risk_and_unknown_is_off_the_scale(scanned: TestClient) -> None:
    risk, observed = _grid(scanned)
    image = np.asarray(Image.open(io.BytesIO(scanned.get("/maps/lab/risk", params={"format": "png"}).content)))
    cells = image.transpose(1, 0, 2)[:, ::-1].reshape(-1, 3).astype(float)  # back to [i, j] order
    luminance = cells @ [0.299, 0.587, 0.114]
    risk, observed = risk.reshape(-1), observed.reshape(-1)
    low, high = observed & (risk < 0.2), observed & (risk > 0.8)
    assert low.any() and high.any()
    assert luminance[low].min() > luminance[high].max() + 50
    known_colours = {tuple(c) for c in cells[observed].astype(int)}
    assert tuple(UNKNOWN_RGB) not in known_colours


def test_png_scale_and_hatching(scanned: TestClient) -> None:
    image = np.asarray(Image.open(io.BytesIO(
        scanned.get("/maps/lab/risk", params={"format": "png", "scale": 4}).content)))
    assert image.shape == (400, 400, 3)
    corner = image[-4:, -4:]  # cell (99, 0) is never observed: hatched grey-blue
    assert (corner == UNKNOWN_RGB).all(axis=2).any() and not (corner == UNKNOWN_RGB).all(axis=2).all()
    assert scanned.get("/maps/lab/risk", params={"format": "png", "scale": 0}).status_code == 422


def test_occupancy_grid_is_row_major_from_the_origin_cell(scanned: TestClient) -> None:
    grid = scanned.get("/maps/lab/occupancy_grid").json()
    assert grid["header"]["frame_id"] == "map"
    info = grid["info"]
    assert (info["width"], info["height"], info["resolution"]) == (100, 100, 0.1)
    assert info["origin"]["position"] == {"x": -5.0, "y": -5.0, "z": 0.0}
    assert info["origin"]["orientation"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
    data = grid["data"]
    assert len(data) == 100 * 100 and all(-1 <= v <= 100 for v in data)

    def at(x: float, y: float) -> int:
        i, j = _cell(x, y)
        return data[j * info["width"] + i]

    # trinary by default, as map_server publishes: the walls are lethal to a costmap with Nav2's defaults
    assert set(data) <= {-1, 0, 100}
    assert at(3.05, 0.0) == 100 and at(1.0, 0.0) == 0 and at(4.9, -4.9) == -1 and at(-2.0, 3.05) == 100
    raw = scanned.get("/maps/lab/occupancy_grid", params={"mode": "probability"}).json()["data"]
    assert 60 < raw[data.index(100)] < 100 and all(-1 <= v < 100 for v in raw)


# ---------------------------------------------------------------- Nav2 map_server, read back faithfully


def _read_pgm(data: bytes) -> np.ndarray:
    """P5 PGM -> (height, width) uint8, header tokens separated by whitespace, '#' comments allowed."""
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end : end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    magic, width, height, maxval = tokens[0], int(tokens[1]), int(tokens[2]), int(tokens[3])
    assert magic == b"P5" and maxval == 255
    pixels = np.frombuffer(data[pos + 1 : pos + 1 + width * height], dtype=np.uint8)
    return pixels.reshape(height, width)


def nav2_load(archive: bytes) -> tuple[dict[str, Any], np.ndarray]:
    """Nav2 loadMapYaml + loadMapFromFile: (yaml, OccupancyGrid data int8 of width * height)."""
    with zipfile.ZipFile(io.BytesIO(archive)) as z:
        meta = yaml.safe_load(z.read("map.yaml"))
        raw = z.read(meta["image"])
    assert len(meta["origin"]) == 3
    if meta["image"].endswith(".pgm"):
        grey, alpha = _read_pgm(raw).astype(float), None
    else:
        img = Image.open(io.BytesIO(raw))
        bands = np.asarray(img.convert("RGBA")).astype(float)
        grey, alpha = bands[..., :3].mean(axis=2), (bands[..., 3] if "A" in img.getbands() else None)
        if meta["mode"] == "trinary" and alpha is not None:  # Nav2 averages alpha in, trinary only
            grey = (bands[..., 0] + bands[..., 1] + bands[..., 2] + bands[..., 3]) / 4
    shade = grey / 255.0
    occ = shade if meta["negate"] else 1.0 - shade
    free, occupied = meta["free_thresh"], meta["occupied_thresh"]
    cell = np.full(occ.shape, -1, dtype=np.int16)
    if meta["mode"] == "trinary":
        cell[occ > occupied] = 100
        cell[occ < free] = 0
    else:
        middle = np.rint((occ - free) / (occupied - free) * 100.0)
        cell = np.where(occ > occupied, 100, np.where(occ < free, 0, middle)).astype(np.int16)
        if alpha is not None:
            cell[alpha != 255] = -1
    height, width = occ.shape
    data = np.empty(width * height, dtype=np.int16)
    rows = np.arange(height)[:, None]
    data[width * (height - rows - 1) + np.arange(width)[None, :]] = cell  # map_io.cpp's index
    return meta, data


def _export(client: TestClient, **params: str) -> tuple[dict[str, Any], np.ndarray]:
    response = client.get("/maps/lab/export/nav2", params=params)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/zip"
    return nav2_load(response.content)


def test_nav2_yaml_has_the_map_geometry_and_thresholds(scanned: TestClient) -> None:
    meta, data = _export(scanned)
    assert meta == {"image": "map.pgm", "mode": "trinary", "resolution": 0.1, "origin": [-5.0, -5.0, 0.0],
                    "negate": 0, "occupied_thresh": 0.6, "free_thresh": FREE}
    assert data.size == 100 * 100


@pytest.mark.parametrize("image_format", ["pgm", "png"])
def test_trinary_export_reads_back_as_our_free_occupied_and_unknown(scanned: TestClient, image_format: str) -> None:
    risk, observed = _grid(scanned)
    _, data = _export(scanned, mode="trinary", format=image_format)
    expected = np.full(risk.shape, -1)
    expected[observed & (risk > 0.6)] = 100
    expected[observed & (risk < FREE)] = 0
    flat = expected.T.reshape(-1)  # data[j * width + i]
    assert np.array_equal(data, flat)
    assert {-1, 0, 100} <= set(np.unique(data).tolist())
    occupancy = scanned.get("/maps/lab/occupancy_grid", params={"mode": "trinary"}).json()["data"]
    assert np.array_equal(data, occupancy)


def test_scale_png_export_keeps_the_grades_and_the_unknown(scanned: TestClient) -> None:
    risk, observed = _grid(scanned)
    meta, data = _export(scanned, mode="scale", format="png")
    assert meta["mode"] == "scale" and meta["image"] == "map.png"
    cost = np.where(risk > 0.6, 100, np.where(risk < FREE, 0, np.rint((risk - FREE) / (0.6 - FREE) * 100)))
    expected = np.where(observed, cost, -1).T.reshape(-1)
    near_threshold = (np.minimum(abs(risk - FREE), abs(risk - 0.6)) < 0.004).T.reshape(-1)
    grey_step = 100 / (255 * (0.6 - FREE))  # the image holds risk in 1/255 steps
    differs = np.abs(data - expected) > grey_step + 0.5
    assert not (differs & ~near_threshold).any()
    assert ((data > 0) & (data < 100)).any()  # graded cells survive
    assert (data[~observed.T.reshape(-1)] == -1).all()


def test_the_scale_occupancy_grid_is_what_map_server_reads_from_the_scale_export(scanned: TestClient) -> None:
    _, exported = _export(scanned, mode="scale", format="png", free_thresh="0.2", occupied_thresh="0.7")
    grid = scanned.get("/maps/lab/occupancy_grid",
                       params={"mode": "scale", "free_thresh": 0.2, "occupied_thresh": 0.7}).json()["data"]
    assert np.array_equal(np.asarray(grid), exported) and ((exported > 0) & (exported < 100)).any()
    for free, occupied in [(0.7, 0.2), (0.5, 0.505)]:  # crossed, or too close for an 8-bit unknown grey
        bad = scanned.get("/maps/lab/occupancy_grid", params={"free_thresh": free, "occupied_thresh": occupied})
        assert bad.status_code == 422 and "free_thresh" in bad.text


def test_exported_files_are_readable_by_another_user_after_unzip(scanned: TestClient) -> None:
    with zipfile.ZipFile(io.BytesIO(scanned.get("/maps/lab/export/nav2").content)) as archive:
        modes = {info.filename: (info.external_attr >> 16) & 0o777 for info in archive.infolist()}
    assert modes == {"map.yaml": 0o644, "map.pgm": 0o644}


def test_scale_pgm_export_writes_unknown_as_risk_one_half(scanned: TestClient) -> None:
    _, observed = _grid(scanned)
    _, data = _export(scanned, mode="scale", format="pgm")
    unknown_cost = data[~observed.T.reshape(-1)]
    assert set(np.unique(unknown_cost).tolist()) == {round((127 / 255 - FREE) / (0.6 - FREE) * 100)}


def test_custom_thresholds_are_written_and_used(scanned: TestClient) -> None:
    risk, observed = _grid(scanned)
    meta, data = _export(scanned, free_thresh="0.1", occupied_thresh="0.9")
    assert (meta["free_thresh"], meta["occupied_thresh"]) == (0.1, 0.9)
    assert np.array_equal(data == 100, (observed & (risk > 0.9)).T.reshape(-1))
    bad = scanned.get("/maps/lab/export/nav2", params={"free_thresh": "0.7", "occupied_thresh": "0.6"})
    assert bad.status_code == 422 and "free_thresh" in bad.json()["detail"]


# ---------------------------------------------------------------- 3-D maps, projected over a z band


@pytest.fixture
def hall(client: TestClient, kit: Any) -> TestClient:
    client.post("/maps", json=kit.MAP_3D)
    points = np.column_stack([np.full(300, 2.5), np.linspace(-1.5, 1.5, 300), np.tile([-0.6, 0.0, 0.4], 100)])
    scan = {"pose": {"position": [0.0, 0.0, 1.0], "orientation": [0, 0, 0, 1]}, "points": points.tolist(),
            "range_max": 10.0}
    assert client.post("/maps/hall/scans", json={"scans": [scan]}).status_code == 200
    return client


def test_a_3d_map_projects_like_octomap_servers_projected_map(hall: TestClient) -> None:
    risk = np.load(io.BytesIO(hall.get("/maps/hall/risk", params={"format": "npy"}).content))
    assert risk.shape == (40, 40, 15)
    full = hall.get("/maps/hall/occupancy_grid").json()
    assert (full["info"]["width"], full["info"]["height"]) == (40, 40)
    i, j = int((2.5 + 4.0) / 0.2), int((0.0 + 4.0) / 0.2)  # the wall's column at x = 2.5, y = 0
    assert full["data"][j * 40 + i] == 100
    above = hall.get("/maps/hall/occupancy_grid", params={"z_min": 2.5, "z_max": 3.0}).json()
    assert set(above["data"]) == {-1}  # nothing was seen up there
    png = Image.open(io.BytesIO(hall.get("/maps/hall/risk", params={"format": "png", "z_max": 1.2}).content))
    assert png.size == (40, 40)
    _, data = nav2_load(hall.get("/maps/hall/export/nav2").content)
    trinary = hall.get("/maps/hall/occupancy_grid", params={"mode": "trinary"}).json()["data"]
    assert np.array_equal(data, trinary) and (data == 100).any()
    assert hall.get("/maps/hall/occupancy_grid", params={"z_min": 2, "z_max": 1}).status_code == 422
