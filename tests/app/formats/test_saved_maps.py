"""A saved Nav2 map read as map_server reads it: every mode, threshold and negate against the port of Nav2 Jazzy's
``loadMapFromFile`` (``tests/app/formats/test_exports.py``), and every kind of bad file refused by name, its sizes
bounded before the work they cost."""

from __future__ import annotations

import io
import zipfile
import zlib
from typing import Any

import httpx
import numpy as np
import pytest
import yaml
from PIL import Image

from app.errors import Invalid, TooLarge
from app.formats import saved_maps
from app.formats.saved_maps import MapCells, open_nav2
from tests.app.formats.test_exports import _std_round, map_io_jazzy, nav2_load

LIMITS: dict[str, int] = {"max_cells": 1_000_000, "max_file_bytes": 8 * 2**20}

# ---------------------------------------------------------------- files as map_saver writes them


def nav2_yaml(**fields: Any) -> bytes:
    """map_saver's YAML (its defaults), with ``fields`` changed; a field given as None is left out."""
    meta: dict[str, Any] = {"image": "map.pgm", "mode": "trinary", "resolution": 0.05, "origin": [-1.0, -2.0, 0.0],
                            "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.25}
    meta.update(fields)
    return yaml.safe_dump({k: v for k, v in meta.items() if v is not None}, sort_keys=False).encode()


def pgm(grey: np.ndarray) -> bytes:
    """A binary PGM of image rows (top row first), with a comment as map_saver writes one."""
    height, width = grey.shape
    return f"P5\n# CREATOR: map_saver.cpp 0.050 m/pix\n{width} {height}\n255\n".encode() + grey.astype(np.uint8).tobytes()


def png(grey: np.ndarray, alpha: np.ndarray | None = None, *, rgba: bool = False) -> bytes:
    """A PNG of image rows: grey, grey + alpha, or (``rgba``) map_saver's scale mode (TrueColorMatte: R = G = B)."""
    out = io.BytesIO()
    if rgba:
        assert alpha is not None
        Image.fromarray(np.stack([grey, grey, grey, alpha], axis=2).astype(np.uint8), mode="RGBA").save(out, "PNG")
    elif alpha is not None:
        Image.fromarray(np.stack([grey, alpha], axis=2).astype(np.uint8), mode="LA").save(out, "PNG")
    else:
        Image.fromarray(grey.astype(np.uint8), mode="L").save(out, "PNG")
    return out.getvalue()


def zipped(files: dict[str, bytes]) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in files.items():
            archive.writestr(name, data)
    return out.getvalue()


def form(parts: dict[str, tuple[str | None, bytes]]) -> tuple[bytes, str]:
    """A multipart/form-data body of ``parts`` (name -> (file name or None, bytes)) and its Content-Type."""
    files = {name: (filename, data) for name, (filename, data) in parts.items() if filename is not None}
    fields = {name: data.decode("latin-1") for name, (filename, data) in parts.items() if filename is None}
    request = httpx.Request("POST", "http://x/", files=files, data=fields or None)
    return request.read(), request.headers["content-type"]


def read_zip(body: bytes, **limits: int) -> saved_maps.SavedMap:
    return open_nav2(body, saved_maps.ZIP, **{**LIMITS, **limits})


def published(cells: MapCells, meta: dict[str, Any]) -> np.ndarray:
    """What map_server publishes of cells read so: ``data[j * width + i]`` (int8, -1 unknown)."""
    p = cells.occupancy[cells.codes]
    values = np.full(p.shape, -1, dtype=np.int16)
    if meta["mode"] == "raw":
        known = ~np.isnan(p)
        values[known] = np.rint(p[known] * 100)
    else:
        values[p == 1.0] = 100
        values[p == 0.0] = 0
        if meta["mode"] == "scale":
            between = ~np.isnan(p) & (p > 0.0) & (p < 1.0)
            free, occupied = meta["free_thresh"], meta["occupied_thresh"]
            scaled = (p[between].astype(np.float32) - np.float32(free)) / np.float32(occupied - free) * np.float32(100)
            values[between] = _std_round(scaled)
    return values.T.reshape(-1).astype(np.int8)


# ---------------------------------------------------------------- what the pixels mean


@pytest.mark.parametrize("mode", ["trinary", "scale", "raw"])
@pytest.mark.parametrize("negate", [0, 1])
@pytest.mark.parametrize("with_alpha", [False, True])
def test_every_pixel_reads_as_map_servers_loader_reads_it(mode: str, negate: int, with_alpha: bool) -> None:
    rng = np.random.default_rng(11)
    grey = np.tile(np.arange(256, dtype=np.uint8), (3, 2))[:, :500]  # every grey, in rows of 500
    alpha = np.where(rng.random(grey.shape) < 0.2, rng.integers(0, 255, grey.shape), 255).astype(np.uint8)
    image, name = (png(grey, alpha), "map.png") if with_alpha else (pgm(grey), "map.pgm")
    for free, occupied in [(0.25, 0.65), (0.45, 0.6), (0.0, 1.0), (0.1234, 0.5678), (0.5, 0.51)]:
        archive = zipped({"map.yaml": nav2_yaml(image=name, mode=mode, negate=negate, free_thresh=free,
                                                occupied_thresh=occupied), name: image})
        meta, expected = nav2_load(archive, loader=map_io_jazzy)
        saved = read_zip(archive)
        assert (saved.width, saved.height) == (500, 3)
        got = published(saved.cells(), meta)
        assert np.array_equal(got, expected), (free, occupied, np.flatnonzero(got != expected)[:5])
    if with_alpha and mode != "raw":  # transparency is unknown in trinary and scale; raw reads the grey alone
        assert (got[(alpha[::-1] < 255).reshape(-1)] == -1).all()


def test_the_map_is_the_image_with_its_top_row_the_highest_y() -> None:
    grey = np.full((2, 3), 254, dtype=np.uint8)
    grey[0, 0] = 0  # top left: the highest y, the lowest x
    saved = read_zip(zipped({"map.yaml": nav2_yaml(), "map.pgm": pgm(grey)}))
    assert (saved.resolution, saved.origin, saved.width, saved.height, saved.frame_id) == \
        (0.05, (-1.0, -2.0), 3, 2, None)
    cells = saved.cells()
    p = cells.occupancy[cells.codes]
    assert p.shape == (3, 2) and p[0, 1] == 1.0 and np.count_nonzero(p == 1.0) == 1 and np.all(p[p != 1.0] == 0.0)


def test_map_savers_grey_205_is_unknown_under_free_thresh_0196_and_free_under_025_as_map_server_reads_it() -> None:
    grey = np.array([[0, 205, 254]], dtype=np.uint8)  # map_saver's occupied, unknown and free
    cells = read_zip(zipped({"map.yaml": nav2_yaml(free_thresh=0.196), "map.pgm": pgm(grey)})).cells()
    p = cells.occupancy[cells.codes].reshape(-1)
    assert p[0] == 1.0 and np.isnan(p[1]) and p[2] == 0.0
    # occ of 205 is 50 / 255 = 0.196: at or below Nav2 map_saver's default free_thresh 0.25, map_server loads it free
    cells = read_zip(zipped({"map.yaml": nav2_yaml(free_thresh=0.25), "map.pgm": pgm(grey)})).cells()
    assert cells.occupancy[cells.codes].reshape(-1).tolist() == [1.0, 0.0, 0.0]


def test_map_savers_scale_png_is_rgba_and_reads_as_its_grey_and_alpha() -> None:
    grey = np.array([[0, 60, 128, 200, 254]], dtype=np.uint8)
    alpha = np.array([[255, 255, 255, 255, 0]], dtype=np.uint8)
    as_rgba = read_zip(zipped({"map.yaml": nav2_yaml(image="map.png", mode="scale"),
                               "map.png": png(grey, alpha, rgba=True)})).cells()
    as_la = read_zip(zipped({"map.yaml": nav2_yaml(image="map.png", mode="scale"), "map.png": png(grey, alpha)})).cells()
    p = as_rgba.occupancy[as_rgba.codes].reshape(-1)
    assert np.array_equal(p, as_la.occupancy[as_la.codes].reshape(-1), equal_nan=True)
    # occ = 1 - grey / 255: 1 (occupied), 0.765 (occupied at 0.65), 0.498 kept, 0.216 (free at 0.25), transparent
    assert p[0] == 1.0 and p[1] == 1.0 and p[2] == pytest.approx(1 - 128 / 255, abs=1e-6) and p[3] == 0.0
    assert np.isnan(p[4])


# ---------------------------------------------------------------- the containers


def test_a_form_of_the_two_files_reads_as_their_zip() -> None:
    grey = np.array([[0, 205, 254], [254, 0, 205]], dtype=np.uint8)
    body, content_type = form({"yaml": ("map.yaml", nav2_yaml()), "image": ("map.pgm", pgm(grey))})
    from_form = open_nav2(body, content_type, **LIMITS).cells()
    from_zip = read_zip(zipped({"map.yaml": nav2_yaml(), "map.pgm": pgm(grey)})).cells()
    assert np.array_equal(from_form.codes, from_zip.codes)
    # the YAML may come as a plain field (curl -F 'yaml=<map.yaml'), the image without a file name
    body, content_type = form({"yaml": (None, nav2_yaml()), "image": ("map.pgm", pgm(grey))})
    assert np.array_equal(open_nav2(body, content_type, **LIMITS).cells().codes, from_zip.codes)


def test_a_zip_of_a_folder_reads_the_image_beside_its_yaml_and_an_absolute_image_by_its_name() -> None:
    grey = np.zeros((1, 2), dtype=np.uint8)
    assert read_zip(zipped({"maps/floor1.yaml": nav2_yaml(image="floor1.pgm"), "maps/floor1.pgm": pgm(grey),
                            "README.txt": b"two floors"})).width == 2
    assert read_zip(zipped({"floor1.yaml": nav2_yaml(image="/home/robot/maps/floor1.pgm"),
                            "floor1.pgm": pgm(grey)})).width == 2


BAD_YAMLS = [
    (b"image: [unclosed", "not YAML"),
    (b"- image\n- map.pgm\n", "not a Nav2 map YAML"),
    (nav2_yaml(negate=None), "lacks negate"),
    (nav2_yaml(free_thresh=None, occupied_thresh=None), "lacks occupied_thresh, free_thresh"),
    (nav2_yaml(image=""), "image must name"),
    (nav2_yaml(resolution=-0.05), "resolution must be a positive"),
    (nav2_yaml(resolution="fine"), "resolution must be a finite number"),
    (nav2_yaml(resolution=float("nan")), "resolution must be a finite number"),
    (nav2_yaml(origin=[1.0, 2.0]), "origin must be [x, y, yaw]"),
    (nav2_yaml(origin=[1.0, "a", 0.0]), "origin[1] must be a finite number"),
    (nav2_yaml(origin=[1.0, 2.0, 0.5]), "origin[2] (yaw) is 0.5"),
    (nav2_yaml(mode="fancy"), "mode must be one of trinary, scale, raw"),
    (nav2_yaml(negate="yes"), "negate must be 0 or 1"),
    (nav2_yaml(free_thresh=0.7, occupied_thresh=0.6), "free_thresh < occupied_thresh"),
    (nav2_yaml(occupied_thresh=1.5), "occupied_thresh <= 1"),
]


@pytest.mark.parametrize(("meta", "says"), BAD_YAMLS)
def test_a_yaml_that_is_not_a_map_is_refused_naming_what_is_wrong(meta: bytes, says: str) -> None:
    with pytest.raises(Invalid) as refused:
        read_zip(zipped({"map.yaml": meta, "map.pgm": pgm(np.zeros((2, 2), dtype=np.uint8))}))
    assert refused.value.message.startswith("map.yaml: ") and says in refused.value.message


BAD_ZIPS = [
    (b"PK\x03\x04 not really", "not a zip file"),
    (zipped({"map.pgm": pgm(np.zeros((2, 2), dtype=np.uint8))}), "holds no .yaml file"),
    (zipped({"a.yaml": nav2_yaml(), "b.yml": nav2_yaml(), "map.pgm": b""}), "holds 2 .yaml files (a.yaml, b.yml)"),
    (zipped({"map.yaml": nav2_yaml(image="other.pgm"), "map.pgm": pgm(np.zeros((2, 2), np.uint8))}),
     "image names 'other.pgm', which the zip does not hold"),
    (zipped({"map.yaml": nav2_yaml(), "map.pgm": b"P5\nthis is no image"}), "map.pgm: not"),
    (zipped({"map.yaml": nav2_yaml(), "map.pgm": b"\x89PNG\r\n\x1a\n garbage"}), "map.pgm: not"),
    (zipped({"map.yaml": nav2_yaml(), "map.pgm": b"GIF89a" + bytes(40)}), "map.pgm: not"),
    (zipped({f"{k}.txt": b"" for k in range(saved_maps.MAX_ZIP_ENTRIES + 1)}), "entries, more than"),
]


@pytest.mark.parametrize(("body", "says"), BAD_ZIPS)
def test_a_zip_without_a_map_or_its_image_is_refused_naming_what_is_wrong(body: bytes, says: str) -> None:
    with pytest.raises(Invalid) as refused:
        read_zip(body)
    assert says in refused.value.message


def test_a_damaged_zip_entry_is_refused_by_name() -> None:
    archive = bytearray(zipped({"map.yaml": nav2_yaml(), "map.pgm": pgm(np.zeros((40, 40), dtype=np.uint8))}))
    start = archive.index(b"map.pgm") + len("map.pgm")  # the image's deflated bytes follow its local header
    archive[start + 2:start + 12] = bytes(10)
    with pytest.raises(Invalid, match="map.pgm"):
        read_zip(bytes(archive))


def test_a_zip_bomb_is_refused_from_its_declared_size_before_anything_is_inflated() -> None:
    inflated = 64 * 2**20  # 64 MiB of zeros deflate to about 64 KiB
    archive = zipped({"map.yaml": nav2_yaml(), "map.pgm": b"P5\n4096 16384\n255\n" + bytes(inflated)})
    assert len(archive) < inflated // 500
    with pytest.raises(TooLarge) as refused:
        read_zip(archive, max_file_bytes=2**20)
    assert refused.value.message.startswith("map.pgm: it inflates to 67,108,8")
    assert "bytes, more than 1,048,576 (FUZZYRISK_MAX_BODY_BYTES)" in refused.value.message
    big_yaml = zipped({"map.yaml": nav2_yaml() + b"#" * saved_maps.MAX_YAML_BYTES, "map.pgm": b""})
    with pytest.raises(TooLarge, match="map.yaml: it inflates to"):
        read_zip(big_yaml)


def test_an_entry_that_inflates_past_its_declared_size_is_cut_there_and_refused() -> None:
    """A zip whose header understates an entry: the reader stops at the declared size, and the CRC check fails."""
    archive = bytearray(zipped({"map.yaml": nav2_yaml(), "map.pgm": bytes(100_000)}))
    central = archive.rindex(b"PK\x01\x02")  # the image's central directory entry: its size at +24
    (declared,) = np.frombuffer(bytes(archive[central + 24:central + 28]), dtype="<u4")
    assert declared == 100_000
    archive[central + 24:central + 28] = (1000).to_bytes(4, "little")
    with pytest.raises((Invalid, TooLarge)):
        read_zip(bytes(archive), max_file_bytes=2000)


BAD_FORMS = [
    ({"image": ("map.pgm", b"")}, "the form has no part 'yaml'"),
    ({"yaml": ("map.yaml", nav2_yaml())}, "the form has no part 'image'"),
    ({"yaml": ("map.yaml", nav2_yaml()), "image": ("floor2.pgm", b"")},
     "image names 'map.pgm', but the 'image' part is 'floor2.pgm'"),
    ({"yaml": ("map.yaml", nav2_yaml()), "image": ("map.pgm", b""), "extra": ("x", b"")},
     "the form's part 'extra' is not one of"),
]


@pytest.mark.parametrize(("parts", "says"), BAD_FORMS)
def test_a_form_without_the_two_files_or_with_another_image_is_refused(parts: Any, says: str) -> None:
    body, content_type = form(parts)
    with pytest.raises(Invalid) as refused:
        open_nav2(body, content_type, **LIMITS)
    assert says in refused.value.message


def test_a_form_without_a_boundary_or_cut_short_is_refused() -> None:
    with pytest.raises(Invalid, match="boundary"):
        open_nav2(b"", "multipart/form-data", **LIMITS)
    body, content_type = form({"yaml": ("map.yaml", nav2_yaml()), "image": ("map.pgm", pgm(np.zeros((2, 2))))})
    with pytest.raises(Invalid, match="the form has no part"):
        open_nav2(body[: len(body) // 2], content_type, **LIMITS)


# ---------------------------------------------------------------- sizes, before the work


def test_a_map_over_the_cell_limit_is_refused_from_the_images_header_before_its_pixels_are_read() -> None:
    header_only = b"P5\n5000 4000\n255\n" + bytes(10)  # 20 M cells declared, 10 bytes of pixels sent
    with pytest.raises(TooLarge) as refused:
        read_zip(zipped({"map.yaml": nav2_yaml(), "map.pgm": header_only}))
    assert "5000 x 4000 = 20,000,000 cells, more than FUZZYRISK_MAX_MAP_CELLS (1,000,000)" in refused.value.message
    small = png(np.zeros((1, 1), dtype=np.uint8))
    at = small.index(b"IHDR")  # a PNG whose header declares 3000 x 3000, with one pixel of data
    ihdr = b"IHDR" + (3000).to_bytes(4, "big") * 2 + small[at + 12:at + 17]
    forged = small[:at] + ihdr + zlib.crc32(ihdr).to_bytes(4, "big") + small[at + 21:]
    with pytest.raises(TooLarge, match="3000 x 3000"):
        read_zip(zipped({"map.yaml": nav2_yaml(image="map.png"), "map.png": forged}))


def test_pixels_cut_short_are_refused_when_decoded() -> None:
    saved = read_zip(zipped({"map.yaml": nav2_yaml(), "map.pgm": b"P5\n100 100\n255\n" + bytes(50)}))
    with pytest.raises(Invalid, match="map.pgm: its pixels cannot be read"):
        saved.cells()


def test_sixteen_bit_images_and_a_box_far_from_the_frame_are_refused() -> None:
    wide = b"P5\n2 2\n65535\n" + bytes(8)
    with pytest.raises(Invalid, match="16-bit"):
        read_zip(zipped({"map.yaml": nav2_yaml(), "map.pgm": wide}))
    with pytest.raises(Invalid, match="local map frame"):
        read_zip(zipped({"map.yaml": nav2_yaml(origin=[2e7, 0.0, 0.0]), "map.pgm": pgm(np.zeros((2, 2)))}))


def test_the_image_is_read_by_map_savers_formats_only() -> None:
    out = io.BytesIO()
    Image.fromarray(np.zeros((4, 4), dtype=np.uint8)).save(out, "TIFF")
    with pytest.raises(Invalid, match="PGM, PNG, BMP"):
        read_zip(zipped({"map.yaml": nav2_yaml(image="map.tif"), "map.tif": out.getvalue()}))
    out = io.BytesIO()
    Image.fromarray(np.zeros((4, 4), dtype=np.uint8)).save(out, "BMP")
    assert read_zip(zipped({"map.yaml": nav2_yaml(image="map.bmp"), "map.bmp": out.getvalue()})).width == 4


def test_deflated_bytes_are_what_the_zip_bomb_check_bounds() -> None:
    """The bound is on inflated bytes: the same image stored (not deflated) passes the same limit."""
    image = pgm(np.zeros((10, 10), dtype=np.uint8))
    assert len(zlib.compress(image)) < len(image)
    stored = io.BytesIO()
    with zipfile.ZipFile(stored, "w", compression=zipfile.ZIP_STORED) as archive:
        archive.writestr("map.yaml", nav2_yaml())
        archive.writestr("map.pgm", image)
    assert read_zip(stored.getvalue(), max_file_bytes=len(image)).width == 10
    with pytest.raises(TooLarge):
        read_zip(stored.getvalue(), max_file_bytes=len(image) - 1)


@pytest.mark.parametrize("image_name", ["map.pgm", "map.png"])
def test_damaged_files_are_refused_as_such_and_nothing_else_escapes(image_name: str) -> None:
    """Bytes flipped anywhere in the zip: each read succeeds or says the file is bad (422 or 413), never more."""
    rng = np.random.default_rng(23)
    grey = rng.integers(0, 256, (30, 40)).astype(np.uint8)
    image = pgm(grey) if image_name.endswith("pgm") else png(grey, np.full_like(grey, 255))
    good = zipped({"map.yaml": nav2_yaml(image=image_name), image_name: image})
    outcomes = {"read": 0, "refused": 0}
    for _ in range(300):
        damaged = bytearray(good)
        for at in rng.integers(0, len(damaged), rng.integers(1, 4)):
            damaged[at] = rng.integers(0, 256)
        try:
            read_zip(bytes(damaged)).cells()
            outcomes["read"] += 1
        except (Invalid, TooLarge):
            outcomes["refused"] += 1
    assert outcomes["refused"] > 0 and sum(outcomes.values()) == 300
