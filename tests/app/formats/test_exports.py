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

from app.formats import exports
from app.formats.exports import NAV2_FREE_THRESH as FREE
from app.formats.exports import UNKNOWN_RGB
from tests.conftest import error_message


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


def _read_image(name: str, raw: bytes) -> tuple[np.ndarray, np.ndarray | None]:
    """(grey uint8, alpha uint8 or None) of a grey PGM or PNG: what map_io.cpp gets from GraphicsMagick's
    ``gray.write(..., "I", CharPixel, ...)`` and, when ``img.matte()``, ``img.write(..., "A", ...)``."""
    if name.endswith(".pgm"):
        return _read_pgm(raw), None
    img = Image.open(io.BytesIO(raw))
    assert img.mode in ("L", "LA"), img.mode  # our exports are grey: intensity is the grey itself
    bands = np.asarray(img)
    return (bands[..., 0], bands[..., 1]) if img.mode == "LA" else (bands, None)


def _std_round(x: np.ndarray) -> np.ndarray:
    """Eigen's ``round()`` on float32 as its SSE ``pround`` computes it: add the float just below 0.5
    with x's sign, then truncate; halves go away from zero (``std::round``), unlike ``np.rint``."""
    below_half = np.frombuffer(np.uint32(0x3EFFFFFF).tobytes(), dtype=np.float32)[0]
    return np.trunc(x + np.copysign(below_half, x)).astype(np.float32)


def map_io_jazzy(mode: str, grey: np.ndarray, alpha: np.ndarray | None, *, negate: bool, free_thresh: float,
                 occupied_thresh: float) -> np.ndarray:
    """Nav2 Jazzy's nav2_map_server/src/map_io.cpp ``loadMapFromFile`` (the Eigen implementation), per
    image row, before the vertical flip. Its statements, in order:

    - ``normalized = gray_matrix.cast<float>() / 255.0f;`` and, ``if (!load_parameters.negate)``,
      ``normalized = (1.0f - normalized.array()).matrix();``
    - ``occupied = (normalized.array() >= load_parameters.occupied_thresh)`` and
      ``free = (normalized.array() <= load_parameters.free_thresh)`` (Eigen compares with the double
      threshold made a float); ``result.setConstant(OCC_GRID_UNKNOWN)``, then
      ``result = (occupied.array() > 0).select(OCC_GRID_OCCUPIED, result)``, then the same for free
    - scale: ``in_between_mask = (normalized.array() > load_parameters.free_thresh) &&
      (normalized.array() < load_parameters.occupied_thresh)``; ``scaled_float =
      ((normalized.array() - load_parameters.free_thresh) / (load_parameters.occupied_thresh -
      load_parameters.free_thresh)) * 100.0f`` (the difference of thresholds is a double made a
      float); ``scaled_int = scaled_float.array().round().cast<int8_t>()``
    - ``if (has_alpha)`` (trinary and scale): ``result = (alpha_array < 255).select(OCC_GRID_UNKNOWN, result)``
    - raw: ``result = gray_matrix.cast<int8_t>()``; values ``< OCC_GRID_FREE || > OCC_GRID_OCCUPIED``
      become ``OCC_GRID_UNKNOWN`` (a uint8 above 127 wraps negative: every pixel above 100 is -1)
    """
    if mode == "raw":
        result = grey.astype(np.uint8).view(np.int8).copy()
        result[(result < 0) | (result > 100)] = -1
        return result
    normalized = grey.astype(np.float32) / np.float32(255.0)
    if not negate:
        normalized = np.float32(1.0) - normalized
    free, occupied = np.float32(free_thresh), np.float32(occupied_thresh)
    result = np.full(grey.shape, -1, dtype=np.int8)
    result[normalized >= occupied] = 100
    result[normalized <= free] = 0
    if mode == "scale":
        between = (normalized > free) & (normalized < occupied)
        scaled = (normalized[between] - free) / np.float32(occupied_thresh - free_thresh) * np.float32(100.0)
        assert scaled.dtype == np.float32
        result[between] = _std_round(scaled).astype(np.int8)
    if alpha is not None:
        result[alpha < 255] = -1
    return result


def map_io_legacy(mode: str, grey: np.ndarray, alpha: np.ndarray | None, *, negate: bool, free_thresh: float,
                  occupied_thresh: float) -> np.ndarray:
    """The per-pixel loop of earlier releases (Humble): double arithmetic, trinary averages alpha into the
    grey, ``occupied_thresh < occ`` / ``occ < free_thresh``, scale ``std::rint``, raw ``std::round(shade * 255)``."""
    channels = [grey.astype(np.float64)] * 3
    if mode == "trinary" and alpha is not None:
        channels.append(alpha.astype(np.float64))  # MaxRGB - alphaQuantum() (an opacity): the alpha
    shade = sum(channels) / len(channels) / 255.0
    occ = shade if negate else 1.0 - shade
    result = np.full(grey.shape, -1, dtype=np.int8)
    if mode == "raw":
        percent = np.round(shade * 255.0)
        inside = (percent >= 0) & (percent <= 100)
        result[inside] = percent[inside].astype(np.int8)
        return result
    if mode == "trinary":
        result[occupied_thresh < occ] = 100
        result[occ < free_thresh] = 0
        return result
    middle = np.rint((occ - free_thresh) / (occupied_thresh - free_thresh) * 100.0)
    result = np.where(occupied_thresh < occ, 100, np.where(occ < free_thresh, 0, middle)).astype(np.int8)
    if alpha is not None:
        result[alpha != 255] = -1
    return result


def nav2_load(archive: bytes, *, loader: Any = map_io_jazzy) -> tuple[dict[str, Any], np.ndarray]:
    """Nav2 loadMapYaml + loadMapFromFile: (yaml, OccupancyGrid data int8 of width * height)."""
    with zipfile.ZipFile(io.BytesIO(archive)) as z:
        meta = yaml.safe_load(z.read("map.yaml"))
        raw = z.read(meta["image"])
    assert len(meta["origin"]) == 3
    assert {"free_thresh", "occupied_thresh", "negate", "resolution"} <= set(meta)  # loadMapYaml needs them all
    grey, alpha = _read_image(meta["image"], raw)
    rows = loader(meta.get("mode", "trinary"), grey, alpha, negate=bool(meta["negate"]),
                  free_thresh=meta["free_thresh"], occupied_thresh=meta["occupied_thresh"])
    # "Flip image vertically": msg.data[width * (height - y - 1) + x] = pixel (x, y)
    return meta, np.ascontiguousarray(rows[::-1]).reshape(-1)


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


def test_custom_thresholds_are_written_and_used(scanned: TestClient) -> None:
    risk, observed = _grid(scanned)
    meta, data = _export(scanned, free_thresh="0.1", occupied_thresh="0.9")
    assert (meta["free_thresh"], meta["occupied_thresh"]) == (0.1, 0.9)
    assert np.array_equal(data == 100, (observed & (risk > 0.9)).T.reshape(-1))
    bad = scanned.get("/maps/lab/export/nav2", params={"free_thresh": "0.7", "occupied_thresh": "0.6"})
    assert bad.status_code == 422 and "free_thresh" in error_message(bad)


def test_scale_pgm_export_is_refused_with_the_reason_and_what_to_use(scanned: TestClient) -> None:
    bad = scanned.get("/maps/lab/export/nav2", params={"mode": "scale", "format": "pgm"})
    assert bad.status_code == 422
    detail = error_message(bad)
    assert "alpha" in detail and "format=png" in detail and "mode=trinary" in detail and "mode=raw" in detail
    with pytest.raises(ValueError, match="alpha"):
        exports.nav2_zip(np.zeros((2, 2), np.float32), np.ones((2, 2), bool), resolution=0.1, origin_xy=(0.0, 0.0),
                         mode="scale", image_format="pgm")


@pytest.mark.parametrize("loader", [map_io_jazzy, map_io_legacy])
def test_no_grey_reads_as_unknown_in_scale_mode_without_alpha(loader: Any) -> None:
    """Why scale + PGM is refused: without alpha every grey loads as 0..100 under any thresholds."""
    greys = np.arange(256, dtype=np.uint8)[None, :]
    for free, occupied in [(0.0, 0.01), (0.25, 0.65), (FREE, 0.6), (0.49, 0.5), (0.5, 0.51), (0.99, 1.0)]:
        cells = loader("scale", greys, None, negate=False, free_thresh=free, occupied_thresh=occupied)
        assert cells.min() >= 0 and cells.max() == 100, (free, occupied)


def _threshold_pairs() -> list[tuple[float, float]]:
    """Every pair of hundredths at least 0.01 apart, written as a client types them."""
    hundredths = [float(f"{k / 100:.2f}") for k in range(101)]
    return [(hundredths[a], hundredths[b]) for a in range(101) for b in range(a + 1, 101)]


def test_scale_grades_are_jazzys_float32_arithmetic_for_every_grey_and_threshold_pair() -> None:
    greys = np.arange(256, dtype=np.uint8)
    differs_from_double_rint = 0
    for free, occupied in _threshold_pairs() + [(FREE, 0.6), (0.123, 0.456), (0.3333, 0.6667)]:
        ours = exports.map_server_scale(greys, free_thresh=free, occupied_thresh=occupied)
        jazzy = map_io_jazzy("scale", greys[None, :], None, negate=False, free_thresh=free,
                             occupied_thresh=occupied)[0]
        assert np.array_equal(ours, jazzy), (free, occupied, np.flatnonzero(ours != jazzy))
        legacy = map_io_legacy("scale", greys[None, :], None, negate=False, free_thresh=free,
                               occupied_thresh=occupied)[0]
        differs_from_double_rint += int((legacy != jazzy).sum())
    assert differs_from_double_rint > 0  # the arithmetic matters: double + rint would be off by 1 somewhere


def test_every_mode_reads_back_exactly_under_every_threshold_pair() -> None:
    """Pixels as ``nav2_zip`` writes them, through the Jazzy loader port, equal ``occupancy_data``: risks on
    every grey step, every hundredth and the thresholds themselves; a quarter of the cells never observed."""
    rng = np.random.default_rng(12)
    base = np.concatenate([np.arange(256) / 255.0, np.arange(101) / 100.0, rng.random(200)])
    pairs = _threshold_pairs() + [(0.123, 0.456), (0.3333, 0.6667), (0.0, 0.0101), (0.98995, 1.0)]
    for free, occupied in pairs:
        risk = np.concatenate([base, [free, occupied, np.nextafter(free, 1), np.nextafter(occupied, 0)]])
        risk = risk.astype(np.float32).reshape(-1, 1)  # an (n, 1) map: one image row
        observed = rng.random(risk.shape) > 0.25
        for mode, grid_mode in (("trinary", "trinary"), ("scale", "scale"), ("raw", "probability")):
            grey, opaque = exports.nav2_pixels(risk, observed, mode=mode, free_thresh=free, occupied_thresh=occupied)
            alpha = np.where(opaque, 255, 0).astype(np.uint8) if mode == "scale" else None  # the PNG's LA
            rows = map_io_jazzy(mode, grey, alpha, negate=False, free_thresh=free, occupied_thresh=occupied)
            loaded = np.ascontiguousarray(rows[::-1]).reshape(-1)
            expected = exports.occupancy_data(risk, observed, mode=grid_mode, free_thresh=free,
                                              occupied_thresh=occupied)
            assert np.array_equal(loaded, expected), (mode, free, occupied)
            assert (loaded[~observed.T.reshape(-1)] == -1).all()


def test_the_rounding_is_halves_away_from_zero_in_float32() -> None:
    x = np.array([0.5, 1.5, 2.5, 49.5, 0.49999997, 99.49999, -0.5, -2.5], dtype=np.float32)
    assert _std_round(x).tolist() == [1.0, 2.0, 3.0, 50.0, 0.0, 99.0, -1.0, -3.0]
    assert np.array_equal(exports._round_half_away(x), _std_round(x))


def test_every_threshold_pair_a_hundredth_apart_is_accepted() -> None:
    hundredths = [float(f"{k / 100:.2f}") for k in range(101)]
    pairs = list(zip(hundredths[:-1], hundredths[1:], strict=True))
    assert len(pairs) == 100  # the 99 (free 0.00 .. 0.98) and (0.99, 1.0)
    assert sum(not free + 0.01 <= occupied for free, occupied in pairs) == 13  # what a plain comparison refuses
    for free, occupied in pairs:
        exports.check_thresholds(free, occupied)  # 0.07 + 0.01 > 0.08 in binary: compared with a tolerance
    for free, occupied in [(0.5, 0.5099), (0.5, 0.5), (0.6, 0.5), (-0.01, 0.5), (0.5, 1.01)]:
        with pytest.raises(ValueError, match="free_thresh"):
            exports.check_thresholds(free, occupied)


@pytest.mark.parametrize("free_int", [5, 14, 28, 46, 68, 93])
def test_the_routes_accept_thresholds_a_hundredth_apart(scanned: TestClient, free_int: int) -> None:
    """Six of the 13 pairs a plain ``free + 0.01 <= occupied`` refuses; the export must also read back."""
    params = {"free_thresh": f"{free_int / 100:.2f}", "occupied_thresh": f"{(free_int + 1) / 100:.2f}"}
    grid = scanned.get("/maps/lab/occupancy_grid", params={"mode": "scale", **params})
    assert grid.status_code == 200, grid.text
    _, data = _export(scanned, mode="scale", format="png", **params)
    assert np.array_equal(data, grid.json()["data"])


# (export mode, format) -> the occupancy_grid mode whose data map_server must publish from it
EXPORTS = [("trinary", "pgm", "trinary"), ("trinary", "png", "trinary"), ("scale", "png", "scale"),
           ("raw", "pgm", "probability"), ("raw", "png", "probability")]
THRESHOLDS = [(FREE, 0.6), (0.25, 0.65), (0.0, 1.0), (0.3, 0.7), (0.4, 0.6), (0.5, 0.51), (0.49, 0.5), (0.03, 0.97),
              (0.1234, 0.5678)]


@pytest.mark.parametrize(("mode", "image_format", "grid_mode"), EXPORTS)
def test_map_server_loads_every_export_as_the_occupancy_grid_says(
        scanned: TestClient, mode: str, image_format: str, grid_mode: str) -> None:
    _, observed = _grid(scanned)
    unknown = ~observed.T.reshape(-1)
    assert unknown.any() and not unknown.all()
    graded = 0
    for free, occupied in THRESHOLDS:
        params = {"free_thresh": repr(free), "occupied_thresh": repr(occupied)}
        meta, data = _export(scanned, mode=mode, format=image_format, **params)
        assert (meta["mode"], meta["free_thresh"], meta["occupied_thresh"]) == (mode, free, occupied)
        grid = scanned.get("/maps/lab/occupancy_grid", params={"mode": grid_mode, **params}).json()["data"]
        assert np.array_equal(data, np.asarray(grid)), (free, occupied, np.flatnonzero(data != np.asarray(grid)))
        assert np.array_equal(data == -1, unknown) or grid_mode == "trinary"  # unknown stays unknown ...
        assert (data[unknown] == -1).all()  # ... and trinary adds the cells between the thresholds
        graded += int(((data > 0) & (data < 100)).sum())
        if mode != "scale":  # earlier map_server releases read trinary and raw files the same
            assert np.array_equal(nav2_load(_export_bytes(scanned, mode=mode, format=image_format, **params),
                                            loader=map_io_legacy)[1], data)
    assert graded > 0 or mode == "trinary"


def _export_bytes(client: TestClient, **params: str) -> bytes:
    response = client.get("/maps/lab/export/nav2", params=params)
    assert response.status_code == 200, response.text
    return response.content


@pytest.mark.parametrize("image_format", ["pgm", "png"])
def test_raw_export_pixels_are_the_probability_grid_and_255_for_unknown(scanned: TestClient,
                                                                       image_format: str) -> None:
    risk, observed = _grid(scanned)
    archive = _export_bytes(scanned, mode="raw", format=image_format)
    with zipfile.ZipFile(io.BytesIO(archive)) as z:
        meta = yaml.safe_load(z.read("map.yaml"))
        grey, alpha = _read_image(meta["image"], z.read(meta["image"]))
    assert meta["mode"] == "raw" and alpha is None
    cells = grey[::-1].T  # back to [i, j]
    assert np.array_equal(cells[~observed], np.full((~observed).sum(), 255))
    assert np.array_equal(cells[observed], np.rint(risk[observed] * 100))
    _, data = nav2_load(archive)
    assert set(np.unique(data).tolist()) - {-1} <= set(range(101)) and (data == -1).sum() == (~observed).sum()


def test_observed_mask_npy_beside_the_risk_npy(scanned: TestClient) -> None:
    _, observed = _grid(scanned)
    response = scanned.get("/maps/lab/risk", params={"format": "npy", "layer": "observed"})
    assert response.status_code == 200 and response.headers["content-type"] == "application/x-npy"
    assert response.headers["x-map-version"] == "1" and response.headers["x-map-origin"] == "-5.0,-5.0"
    assert response.headers["content-disposition"] == 'attachment; filename="lab-observed-v1.npy"'
    mask = np.load(io.BytesIO(response.content), allow_pickle=False)
    assert mask.dtype == np.bool_ and mask.shape == (100, 100) and np.array_equal(mask, observed)
    risk = np.load(io.BytesIO(scanned.get("/maps/lab/risk", params={"format": "npy", "layer": "risk"}).content))
    assert risk.dtype == np.float32 and (risk[~mask] == 0.5).all()
    for other in ("json", "png"):
        bad = scanned.get("/maps/lab/risk", params={"format": other, "layer": "observed"})
        assert bad.status_code == 422 and "format=npy" in error_message(bad)
    assert scanned.get("/maps/lab/risk", params={"format": "npy", "layer": "cost"}).status_code == 422
    assert scanned.get("/maps/nope/risk", params={"format": "npy", "layer": "observed"}).status_code == 404


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


def test_the_occupancy_values_are_written_as_json_by_numpy() -> None:
    import json

    import numpy as np
    import pytest

    from app.formats.exports import int8_json_array

    values = np.arange(-1, 101, dtype=np.int8).repeat(3)
    assert json.loads(int8_json_array(values)) == values.tolist()
    assert int8_json_array(np.array([], np.int8)) == b"[]"
    with pytest.raises(ValueError, match="-1..100"):
        int8_json_array(np.array([101], np.int16))
