"""A saved Nav2 map in: ``map.yaml`` and its image (a zip, or two multipart parts) read as map_server reads them.

The YAML as ``loadMapYaml`` takes it (``image``, ``resolution``, ``origin``, ``negate``,
``occupied_thresh``, ``free_thresh``, optional ``mode``), the pixels as Nav2 Jazzy's
``loadMapFromFile`` classes them (``app.formats.exports`` writes what it reads back): grey
``g``, ``occ = 1 - g / 255`` in float32 (``g / 255`` with ``negate``), ``trinary`` occupied from
``occ >= occupied_thresh``, free up to ``occ <= free_thresh`` (applied second), the rest unknown;
``scale`` the same ends and ``occ`` kept between them; in both a pixel with alpha below 255 is
unknown; ``raw`` the grey itself as a percentage, anything above 100 unknown (alpha and ``negate``
unused). A colour image is made grey as GraphicsMagick does (Rec. 601 luma).

Every size is bounded before the work it costs: the zip's entries by what they declare before
one is extracted, the image's cells from its header before its pixels are decoded. A file that
is not what it should be raises ``Invalid`` (422) naming the file and the field; a size over a
limit ``TooLarge`` (413) naming the setting.
"""

from __future__ import annotations

import io
import math
import posixpath
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError
from python_multipart.multipart import MultipartParser, parse_options_header

from app.errors import Invalid, TooLarge, UnsupportedMediaType
from fuzzyocc import GridSpec

ZIP = "application/zip"
#: What some clients (Windows' own) call a zip.
X_ZIP = "application/x-zip-compressed"
MULTIPART = "multipart/form-data"
#: The multipart parts of a saved map: the YAML, and the image it names.
YAML_PART, IMAGE_PART = "yaml", "image"
#: Largest ``map.yaml``: map_saver's is about 130 bytes.
MAX_YAML_BYTES = 64 * 1024
#: Most entries of a zip looked through for the map (a zipped folder of one map holds two or three).
MAX_ZIP_ENTRIES = 64
#: The image formats read: map_saver's (``BLESSED_FORMATS``), by Pillow's names. Pillow is asked for
#: these only, so that no other plugin (one that would run an external program) sees the file.
IMAGE_FORMATS = ("PPM", "PNG", "BMP")
MODES = ("trinary", "scale", "raw")
#: The code of a pixel map_server reads as unknown whatever its grey (alpha below 255, trinary and scale).
TRANSPARENT = 256


@dataclass(frozen=True)
class MapCells:
    """A saved map's cells: a code per cell and the occupancy probability of each code.

    ``codes`` is uint16 indexed ``[i, j]`` along x, y; ``occupancy[code]`` is in [0, 1], exactly
    1.0 for occupied and 0.0 for free, NaN for unknown.
    """

    codes: np.ndarray
    occupancy: np.ndarray


@dataclass(frozen=True)
class SavedMap:
    """A saved map opened: its geometry read and checked, its cells decoded by ``cells()``.

    ``origin`` is the corner of cell (0, 0), metres; ``frame_id`` the frame the file names (None:
    none, as in a Nav2 YAML).
    """

    resolution: float
    origin: tuple[float, float]
    width: int
    height: int
    frame_id: str | None
    decode: Callable[[], MapCells]

    def cells(self) -> MapCells:
        """The cells, decoded now (bounded by the size checked when the file was opened)."""
        cells = self.decode()
        if cells.codes.shape != (self.width, self.height):  # cannot happen: a bug, not the client's file
            raise RuntimeError(f"decoded {cells.codes.shape} cells, expected {(self.width, self.height)}")
        return cells


def check_geometry(where: str, resolution: float, origin: tuple[float, float], width: int, height: int,
                   max_cells: int) -> None:
    """``TooLarge`` past ``FUZZYRISK_MAX_MAP_CELLS``, ``Invalid`` for a grid no map can have (checked before the cells
    are decoded)."""
    if width < 1 or height < 1:
        raise Invalid(f"{where}: the map is {width} x {height} cells; it needs at least one")
    cells = width * height
    if cells > max_cells:
        raise TooLarge(f"{where}: the map is {width} x {height} = {cells:,} cells, more than "
                       f"FUZZYRISK_MAX_MAP_CELLS ({max_cells:,})")
    try:
        spec = GridSpec(origin=origin, size=(width * resolution, height * resolution), resolution=resolution,
                        max_cells=max_cells)
    except ValueError as exc:
        raise Invalid(f"{where}: {exc}") from None
    if spec.shape != (width, height):  # size / resolution off by more than GridSpec's tolerance: a map of other cells
        raise Invalid(f"{where}: {width} x {height} cells of {resolution!r} m do not make a grid of whole cells here "
                      f"({spec.shape[0]} x {spec.shape[1]}); resample the map to another resolution")


# ---------------------------------------------------------------- the two containers


def open_nav2(body: bytes, content_type: str, *, max_cells: int, max_file_bytes: int) -> SavedMap:
    """A Nav2 map from a zip (``ZIP``) or a multipart body (``YAML_PART`` and ``IMAGE_PART``)."""
    media = content_type.split(";")[0].strip().lower()
    if media in (ZIP, X_ZIP):
        yaml_name, yaml_bytes, image_name, image_bytes = _from_zip(body, max_file_bytes)
    elif media == MULTIPART:
        yaml_name, yaml_bytes, image_name, image_bytes = _from_multipart(body, content_type)
    else:  # the caller sends only these here
        raise UnsupportedMediaType(f"Content-Type {media!r} is not a saved Nav2 map")
    return _open(yaml_name, yaml_bytes, image_name, image_bytes, max_cells)


def _from_zip(body: bytes, max_file_bytes: int) -> tuple[str, bytes, str, bytes]:
    """(YAML name, YAML, image name, image) of a zip, every size bounded by what the entries declare first."""
    try:
        archive = zipfile.ZipFile(io.BytesIO(body))
    except Exception as exc:  # noqa: BLE001 - BadZipFile, ValueError, NotImplementedError...: the body's fault
        raise Invalid(f"body: not a zip file ({exc}); send map.yaml and its image zipped, or as a multipart "
                      f"form of '{YAML_PART}' and '{IMAGE_PART}'") from None
    with archive:
        entries = archive.infolist()
        if len(entries) > MAX_ZIP_ENTRIES:
            raise Invalid(f"body: the zip holds {len(entries)} entries, more than {MAX_ZIP_ENTRIES}: zip the map's "
                          "YAML and image alone")
        files = [e for e in entries if e.filename and not e.is_dir()]
        yamls = [e for e in files if e.filename.lower().endswith((".yaml", ".yml"))
                 and not posixpath.basename(e.filename).startswith("._")]  # macOS' resource forks are not maps
        if len(yamls) != 1:
            found = "no .yaml file" if not yamls else f"{len(yamls)} .yaml files ({', '.join(e.filename for e in yamls)})"
            raise Invalid(f"body: the zip holds {found}; it must hold one map's YAML (map.yaml) and its image")
        meta_entry = yamls[0]
        yaml_bytes = _extract(archive, meta_entry, MAX_YAML_BYTES, "the YAML's limit")
        image = _image_name(meta_entry.filename, yaml_bytes)
        folder = posixpath.dirname(meta_entry.filename)
        # map_server reads a relative image from the YAML's folder; an absolute one (a robot's disk) by its name there
        wanted = posixpath.normpath(posixpath.join(folder, image if not image.startswith("/")
                                                   else posixpath.basename(image)))
        by_name = {posixpath.normpath(e.filename): e for e in files}
        if wanted not in by_name:
            held = ", ".join(sorted(by_name)[:8])
            raise Invalid(f"{meta_entry.filename}: image names {image!r}, which the zip does not hold as {wanted!r} "
                          f"(it holds {held})")
        entry = by_name[wanted]
        image_bytes = _extract(archive, entry, max_file_bytes, "FUZZYRISK_MAX_BODY_BYTES")
    return meta_entry.filename, yaml_bytes, entry.filename, image_bytes


def _extract(archive: zipfile.ZipFile, entry: zipfile.ZipInfo, limit: int, what: str) -> bytes:
    """An entry's bytes, refused from its declared size before a byte is inflated (a zip bomb inflates nothing)."""
    if entry.file_size > limit:
        raise TooLarge(f"{entry.filename}: it inflates to {entry.file_size:,} bytes, more than {limit:,} ({what})")
    try:
        with archive.open(entry) as stream:
            data = stream.read(limit + 1)  # the reader stops at the declared size: one more byte shows a liar
    except Exception as exc:  # noqa: BLE001 - a damaged, encrypted or unsupported entry: the body's fault
        raise Invalid(f"{entry.filename}: cannot be extracted ({exc})") from None
    if len(data) > limit:
        raise TooLarge(f"{entry.filename}: it inflates to more than {limit:,} bytes ({what})")
    return data


def _from_multipart(body: bytes, content_type: str) -> tuple[str, bytes, str, bytes]:
    """(YAML name, YAML, image name, image) of a multipart form; the image's file name must be the one the YAML
    names (map_saver writes both; a mismatch is two maps mixed up)."""
    parts = _multipart_parts(body, content_type)
    for part in (YAML_PART, IMAGE_PART):
        if part not in parts:
            raise Invalid(f"body: the form has no part '{part}'; send map.yaml as '{YAML_PART}' and its image as "
                          f"'{IMAGE_PART}'")
    yaml_name, yaml_bytes = parts[YAML_PART]
    yaml_name = yaml_name or "map.yaml"
    if len(yaml_bytes) > MAX_YAML_BYTES:
        raise TooLarge(f"{yaml_name}: {len(yaml_bytes):,} bytes, more than {MAX_YAML_BYTES:,} (the YAML's limit)")
    image = posixpath.basename(_image_name(yaml_name, yaml_bytes))
    image_name, image_bytes = parts[IMAGE_PART]
    if image_name is not None and posixpath.basename(image_name.replace("\\", "/")) != image:
        raise Invalid(f"{yaml_name}: image names {image!r}, but the '{IMAGE_PART}' part is {image_name!r}: send "
                      "the image that YAML names")
    return yaml_name, yaml_bytes, image_name or image, image_bytes


def _multipart_parts(body: bytes, content_type: str) -> dict[str, tuple[str | None, bytes]]:
    """Part name -> (file name or None, bytes) of a ``multipart/form-data`` body; ``Invalid`` for anything else in
    it (a part of another name, one twice, a body cut short)."""
    _, params = parse_options_header(content_type)
    boundary = params.get(b"boundary")
    if not boundary:
        raise Invalid("Content-Type: multipart/form-data without a boundary")
    parts: dict[str, tuple[str | None, bytes]] = {}
    headers: dict[bytes, bytes] = {}
    field: list[bytes] = []
    value: list[bytes] = []
    data: list[bytes] = []

    def header_end() -> None:
        headers[b"".join(field).lower()] = b"".join(value)
        field.clear()
        value.clear()

    def part_end() -> None:
        _, disposition = parse_options_header(headers.get(b"content-disposition", b""))
        name = disposition.get(b"name", b"").decode("utf-8", "replace")
        filename = disposition.get(b"filename")
        if name not in (YAML_PART, IMAGE_PART):
            raise Invalid(f"body: the form's part {name!r} is not one of '{YAML_PART}', '{IMAGE_PART}'")
        if name in parts:
            raise Invalid(f"body: the form holds the part '{name}' twice")
        parts[name] = (None if filename is None else filename.decode("utf-8", "replace"), b"".join(data))
        headers.clear()
        data.clear()

    parser = MultipartParser(boundary, {
        "on_part_begin": lambda: None,
        "on_header_field": lambda d, s, e: field.append(d[s:e]),
        "on_header_value": lambda d, s, e: value.append(d[s:e]),
        "on_header_end": header_end,
        "on_part_data": lambda d, s, e: data.append(d[s:e]),
        "on_part_end": part_end,
    })
    try:
        parser.write(body)
        parser.finalize()
    except Invalid:
        raise
    except Exception as exc:  # noqa: BLE001 - the parser's errors (MultipartParseError, ...) are the body's fault
        raise Invalid(f"body: not a multipart/form-data body of that boundary ({exc})") from None
    return parts


# ---------------------------------------------------------------- the YAML and the image


@dataclass(frozen=True)
class _Meta:
    image: str
    mode: str
    resolution: float
    origin: tuple[float, float]
    negate: bool
    occupied_thresh: float
    free_thresh: float


def _image_name(where: str, yaml_bytes: bytes) -> str:
    return _meta(where, yaml_bytes).image


def _meta(where: str, yaml_bytes: bytes) -> _Meta:
    """The fields map_server's ``loadMapYaml`` reads, checked; ``Invalid`` naming the field for a file it would not
    load, or one this service cannot (a rotated origin)."""
    try:
        doc = yaml.safe_load(yaml_bytes)
    except yaml.YAMLError as exc:
        raise Invalid(f"{where}: not YAML ({str(exc).splitlines()[0]})") from None
    required = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh")
    if not isinstance(doc, dict):
        raise Invalid(f"{where}: not a Nav2 map YAML (it holds a {type(doc).__name__}, not the keys "
                      f"{', '.join(required)})")
    missing = [key for key in required if key not in doc]
    if missing:
        raise Invalid(f"{where}: not a Nav2 map YAML: it lacks {', '.join(missing)} (map_server needs "
                      f"{', '.join(required)})")
    image = doc["image"]
    if not isinstance(image, str) or not image.strip():
        raise Invalid(f"{where}: image must name the image file, got {image!r}")
    resolution = _number(where, "resolution", doc["resolution"])
    if resolution <= 0.0:
        raise Invalid(f"{where}: resolution must be a positive number of metres per cell, got {resolution!r}")
    origin = doc["origin"]
    if not isinstance(origin, list) or len(origin) != 3:
        raise Invalid(f"{where}: origin must be [x, y, yaw] (3 values, as map_server reads it), got {origin!r}")
    x, y, yaw = (_number(where, f"origin[{k}]", v) for k, v in enumerate(origin))
    if yaw != 0.0:
        raise Invalid(f"{where}: origin[2] (yaw) is {yaw!r}: a rotated map is not supported (this service's grids "
                      "are aligned with their frame); rotate the image and set the yaw to 0, or publish a "
                      "transform from the map's frame")
    negate = doc["negate"]
    if isinstance(negate, bool):
        negated = negate
    elif isinstance(negate, int):
        negated = negate != 0
    else:
        raise Invalid(f"{where}: negate must be 0 or 1 (or a boolean), got {negate!r}")
    occupied = _number(where, "occupied_thresh", doc["occupied_thresh"])
    free = _number(where, "free_thresh", doc["free_thresh"])
    if not 0.0 <= free < occupied <= 1.0:
        raise Invalid(f"{where}: need 0 <= free_thresh < occupied_thresh <= 1, got free_thresh {free!r} and "
                      f"occupied_thresh {occupied!r}")
    mode = doc.get("mode", "trinary")
    if not isinstance(mode, str) or mode.lower() not in MODES:
        raise Invalid(f"{where}: mode must be one of {', '.join(MODES)} (map_server's), got {mode!r}")
    return _Meta(image=image.strip(), mode=mode.lower(), resolution=resolution, origin=(x, y), negate=negated,
                 occupied_thresh=occupied, free_thresh=free)


def _number(where: str, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise Invalid(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _open(yaml_name: str, yaml_bytes: bytes, image_name: str, image_bytes: bytes, max_cells: int) -> SavedMap:
    meta = _meta(yaml_name, yaml_bytes)
    try:
        image = Image.open(io.BytesIO(image_bytes), formats=IMAGE_FORMATS)  # the header only
    except UnidentifiedImageError:
        raise Invalid(f"{image_name}: not an image of the formats map_saver writes (PGM, PNG, BMP)") from None
    except Image.DecompressionBombError as exc:
        raise TooLarge(f"{image_name}: {exc}") from None
    except (OSError, ValueError, SyntaxError, EOFError) as exc:
        raise Invalid(f"{image_name}: not a readable image ({exc})") from None
    width, height = image.size
    check_geometry(image_name, meta.resolution, meta.origin, width, height, max_cells)
    if image.mode not in ("1", "L", "LA", "P", "PA", "RGB", "RGBA"):
        raise Invalid(f"{image_name}: an image of mode {image.mode} (16-bit or float pixels); save it as 8-bit grey")
    return SavedMap(resolution=meta.resolution, origin=meta.origin, width=width, height=height, frame_id=None,
                    decode=lambda: _cells(image, image_name, meta))


def _cells(image: Image.Image, image_name: str, meta: _Meta) -> MapCells:
    """The image's pixels as map_server classes them (module doc)."""
    try:
        alpha = meta.mode != "raw" and image.has_transparency_data
        pixels = np.asarray(image.convert("LA" if alpha else "L"))
    except (OSError, ValueError, SyntaxError, EOFError, zlib.error) as exc:  # truncated or damaged pixel data
        raise Invalid(f"{image_name}: its pixels cannot be read ({exc})") from None
    grey = (pixels[..., 0] if alpha else pixels).astype(np.uint16)
    if alpha:
        grey[pixels[..., 1] < 255] = TRANSPARENT
    occupancy = np.full(TRANSPARENT + 1, np.nan)
    levels = np.arange(256)
    if meta.mode == "raw":
        occupancy[:101] = levels[:101] / 100.0
    else:
        # Jazzy's arithmetic: float32, the double thresholds compared as floats (exports.map_server_scale)
        shade = levels.astype(np.float32) / np.float32(255.0)
        occ = shade if meta.negate else np.float32(1.0) - shade
        between = (occ > np.float32(meta.free_thresh)) & (occ < np.float32(meta.occupied_thresh))
        if meta.mode == "scale":
            occupancy[:256][between] = occ[between].astype(np.float64)
        occupancy[:256][occ >= np.float32(meta.occupied_thresh)] = 1.0
        occupancy[:256][occ <= np.float32(meta.free_thresh)] = 0.0
    # image rows run down from the highest y: cell (i, j) is pixel (i, height - 1 - j)
    return MapCells(codes=np.ascontiguousarray(grey[::-1].T), occupancy=occupancy)
