"""Risk grids to files people and ROS tools read: PNG, .npy, Nav2 map_server YAML + image, OccupancyGrid.

Pure functions over numpy arrays indexed ``[i, j]`` along x, y (the grid
convention); nothing here knows about maps or HTTP. Images put the highest y in
the top row, x to the right, as a Nav2 PGM does.
"""

from __future__ import annotations

import functools
import io
import time
import zipfile
from typing import Literal

import numpy as np
import yaml
from PIL import Image, PngImagePlugin

from fuzzyocc.grid import RISK_CODES, RISK_STEP

#: Thresholds of every occupancy export (Nav2 YAML and image, OccupancyGrid) unless asked otherwise.
#: Occupied above 0.6, the planner's default ``max_risk``: what a default plan refuses to enter,
#: Nav2 sees as occupied (with the default engine, a wall seen once reads 0.7). Free below 0.45:
#: more free than occupied evidence (the default engine's cell seen free once reads 0.4, twice
#: 0.3; map_saver's 0.25 would export space seen free once or twice as unknown). Unknown is 0.5.
NAV2_OCCUPIED_THRESH = 0.6
NAV2_FREE_THRESH = 0.45
#: Smallest ``occupied_thresh - free_thresh``: a trinary image needs an 8-bit grey (steps of 1/255)
#: strictly between the thresholds for "unknown"; 0.01 leaves two or three.
MIN_THRESH_GAP = 0.01
#: Slack of the gap comparison: 0.07 + 0.01 > 0.08 in binary floating point, yet the gap is 0.01.
_THRESH_GAP_TOLERANCE = 1e-9
#: The pixel of an unknown cell in a ``raw`` image: map_server reads any pixel above 100 as -1
#: (map_saver writes 255 too).
RAW_UNKNOWN_PIXEL = 255

Nav2Mode = Literal["trinary", "scale", "raw"]

#: Never-observed cells in the PNG: a grey-blue that is not on the risk scale, hatched when scale >= 4.
UNKNOWN_RGB = (138, 154, 181)
UNKNOWN_HATCH_RGB = (104, 118, 143)

# ColorBrewer YlOrRd-like ramp from white (risk 0) to dark crimson (risk 1): sequential,
# readable in grey print, and far from the grey-blue of unknown space. Pale up to 0.4 (the default
# engine's space seen free once), orange at 0.6 (occupied for a default plan and the exports).
_RAMP_AT = np.array([0.0, 0.4, 0.6, 0.8, 1.0])
_RAMP_RGB = np.array(
    [[255, 255, 255], [254, 230, 150], [253, 141, 60], [222, 35, 32], [110, 0, 30]], dtype=np.float64
)
RISK_LUT = np.stack(
    [np.interp(np.linspace(0.0, 1.0, 256), _RAMP_AT, _RAMP_RGB[:, c]) for c in range(3)], axis=1
).round().astype(np.uint8)


def project_z(
    risk: np.ndarray,
    observed: np.ndarray,
    *,
    origin_z: float,
    resolution: float,
    z_min: float | None = None,
    z_max: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Project a 3-D grid to 2-D over a z band, as octomap_server's projected map does.

    A column's risk is the largest risk among its *observed* cells whose centre lies in
    ``[z_min, z_max]``; a column with none is unknown (risk 0.5, not observed).

    Parameters
    ----------
    risk : (nx, ny, nz) float32
    observed : (nx, ny, nz) bool
    origin_z, resolution : float
        Grid geometry along z, metres.
    z_min, z_max : float or None
        Band, metres; None = unbounded.

    Returns
    -------
    (nx, ny) float32 risk and (nx, ny) bool observed.
    """
    centres = origin_z + (np.arange(risk.shape[2]) + 0.5) * resolution
    band = np.ones(risk.shape[2], dtype=bool)
    if z_min is not None:
        band &= centres >= z_min
    if z_max is not None:
        band &= centres <= z_max
    seen = observed[:, :, band]
    values = np.where(seen, risk[:, :, band], np.float32(-1.0))
    projected = values.max(axis=2, initial=np.float32(-1.0))
    column_seen = seen.any(axis=2)
    return np.where(column_seen, projected, np.float32(0.5)).astype(np.float32), column_seen


def _image_rows(grid: np.ndarray) -> np.ndarray:
    """[i, j] grid -> image rows (top row = highest y)."""
    return np.ascontiguousarray(grid.T[::-1])


def risk_png(
    risk: np.ndarray, observed: np.ndarray, *, scale: int = 1, text: dict[str, str] | None = None
) -> bytes:
    """A colour PNG of a 2-D risk grid: one ``scale`` x ``scale`` block a cell.

    Risk runs white (0) -> yellow -> orange -> red -> dark crimson (1); never-observed
    cells are flat grey-blue (hatched from ``scale >= 4``), a colour not on the scale.
    """
    levels = np.rint(np.clip(risk, 0.0, 1.0) * 255.0).astype(np.uint8)
    rgb = RISK_LUT[_image_rows(levels)]
    unknown = _image_rows(~observed)
    if scale > 1:
        rgb = rgb.repeat(scale, axis=0).repeat(scale, axis=1)
        unknown = unknown.repeat(scale, axis=0).repeat(scale, axis=1)
    rgb[unknown] = UNKNOWN_RGB
    if scale >= 4:
        rows, cols = np.indices(unknown.shape)
        rgb[unknown & ((rows + cols) % 4 == 0)] = UNKNOWN_HATCH_RGB
    info = PngImagePlugin.PngInfo()
    for key, value in (text or {}).items():
        info.add_text(key, value)
    out = io.BytesIO()
    Image.fromarray(rgb, mode="RGB").save(out, format="PNG", pnginfo=info)
    return out.getvalue()


def npy_bytes(array: np.ndarray) -> bytes:
    """``array`` as a ``.npy`` file (``np.load`` reads it back exactly)."""
    out = io.BytesIO()
    np.save(out, array, allow_pickle=False)
    return out.getvalue()


def check_thresholds(free_thresh: float, occupied_thresh: float) -> None:
    """Raise ValueError unless ``0 <= free_thresh``, ``free_thresh + 0.01 <= occupied_thresh <= 1``.

    The gap is compared with a tolerance of 1e-9: every pair of hundredths 0.01 apart passes (a plain
    ``free + 0.01 <= occupied`` refuses 13 of the 99, e.g. 0.07 and 0.08).
    """
    if not (0.0 <= free_thresh and occupied_thresh <= 1.0
            and occupied_thresh - free_thresh >= MIN_THRESH_GAP - _THRESH_GAP_TOLERANCE):
        raise ValueError(f"need 0 <= free_thresh, free_thresh + 0.01 <= occupied_thresh <= 1, got {free_thresh} "
                         f"and {occupied_thresh}")


def check_nav2_format(mode: str, image_format: str) -> None:
    """Raise ValueError for a mode and image format whose files map_server would not read as our map.

    ``scale`` + ``pgm``: in scale mode map_server marks a cell unknown only by its alpha, and a PGM
    has none; every grey reads as 0..100 (risk 0.5 reads 71 at the default thresholds), so no PGM
    can say "never observed".
    """
    if mode == "scale" and image_format == "pgm":
        raise ValueError("mode=scale cannot be written as a PGM: map_server's scale mode reads unknown only from "
                         "transparency and PGM has no alpha channel, so never-observed cells would load as "
                         "observed; use format=png (unknown cells transparent), or mode=trinary or mode=raw")


def _scale_grey(risk: np.ndarray) -> np.ndarray:
    """The grey ``round(255 * (1 - risk))`` of a scale-mode image (uint8)."""
    return np.rint(255.0 * (1.0 - np.clip(risk, 0.0, 1.0))).astype(np.uint8)


def _round_half_away(x: np.ndarray) -> np.ndarray:
    """``std::round`` (what Eigen's ``round()`` does): halves away from zero, unlike ``np.rint``."""
    wide = x.astype(np.float64)  # exact for float32 input: adding 0.5 rounds nothing
    return np.copysign(np.floor(np.abs(wide) + 0.5), wide)


def map_server_scale(grey: np.ndarray, *, free_thresh: float, occupied_thresh: float) -> np.ndarray:
    """What Nav2 Jazzy's map_server makes of opaque 8-bit greys in ``mode: scale``, ``negate: 0`` (int8).

    A port of ``loadMapFromFile`` in nav2_map_server/src/map_io.cpp (the Eigen implementation):
    float32 throughout, the double thresholds converted to float as Eigen does with a scalar,
    ``occ >= occupied`` 100, ``occ <= free`` 0 (applied second), strictly between
    ``round((occ - free) / (occupied - free) * 100)`` with halves away from zero. Transparency
    (unknown) is the caller's business.
    """
    occ = np.float32(1.0) - np.asarray(grey).astype(np.float32) / np.float32(255.0)
    free, occupied = np.float32(free_thresh), np.float32(occupied_thresh)
    span = np.float32(occupied_thresh - free_thresh)  # subtracted in double, then made a float scalar
    values = np.full(occ.shape, -1, dtype=np.int8)
    values[occ >= occupied] = 100
    values[occ <= free] = 0
    between = (occ > free) & (occ < occupied)
    scaled = (occ[between] - free) / span * np.float32(100.0)
    values[between] = _round_half_away(scaled).astype(np.int8)
    return values


@functools.lru_cache(maxsize=32)
def occupancy_lut(mode: Literal["trinary", "scale", "probability"] = "trinary",
                  free_thresh: float = NAV2_FREE_THRESH, occupied_thresh: float = NAV2_OCCUPIED_THRESH) -> np.ndarray:
    """``occupancy_data`` of every risk code: entry ``k`` is the value of an observed cell of risk
    ``k * RISK_STEP`` (``OccupancyMap.plane_lookup``'s table; read-only, kept per mode and thresholds)."""
    risk = np.arange(RISK_CODES, dtype=np.float32) * np.float32(RISK_STEP)
    lut = occupancy_data(risk, np.ones(RISK_CODES, dtype=np.bool_), mode=mode, free_thresh=free_thresh,
                         occupied_thresh=occupied_thresh)
    lut.flags.writeable = False
    return lut


def occupancy_data(
    risk: np.ndarray,
    observed: np.ndarray,
    *,
    mode: Literal["trinary", "scale", "probability"] = "trinary",
    free_thresh: float = NAV2_FREE_THRESH,
    occupied_thresh: float = NAV2_OCCUPIED_THRESH,
) -> np.ndarray:
    """``nav_msgs/OccupancyGrid.data``: int8, ``data[j * width + i]``, -1 for never-observed cells.

    As Nav2's map_server reads the ``nav2_zip`` image of the same mode: ``trinary`` 100 above
    ``occupied_thresh``, 0 below ``free_thresh``, -1 between; ``scale`` (the PNG) what
    map_server's scale mode makes of the image's 8-bit grey ``round(255 * (1 - risk))``
    (``map_server_scale``: 100 from ``occupied_thresh`` up, 0 up to ``free_thresh``, graded
    between). ``probability``: the raw ``round(100 * risk)``, which is also what map_server
    loads from the ``raw`` export; for tools of one's own: no cell below risk 0.995 reaches 100,
    so a costmap with Nav2's defaults (lethal at 100) would see almost none of it as lethal.
    """
    if mode == "probability":
        values = np.rint(np.clip(risk, 0.0, 1.0) * 100.0).astype(np.int8)
    elif mode == "trinary":
        values = np.full(risk.shape, -1, dtype=np.int8)
        values[risk > occupied_thresh] = 100
        values[risk < free_thresh] = 0
    else:
        values = map_server_scale(_scale_grey(risk), free_thresh=free_thresh, occupied_thresh=occupied_thresh)
    values[~observed] = -1
    # row-major from the origin cell: j (y) is the slow axis
    return np.ascontiguousarray(values.T).reshape(-1)


def nav2_pixels(
    risk: np.ndarray,
    observed: np.ndarray,
    *,
    mode: Nav2Mode,
    free_thresh: float = NAV2_FREE_THRESH,
    occupied_thresh: float = NAV2_OCCUPIED_THRESH,
) -> tuple[np.ndarray, np.ndarray]:
    """Grey levels (uint8, image rows) and an opacity mask that Nav2's map_server reads back as our map.

    Nav2 reads ``occ = 1 - p / 255`` (negate 0). ``trinary``: occupied (risk above
    ``occupied_thresh``) is 0, free (below ``free_thresh``) is 255, the rest is the grey whose
    ``occ`` lies midway between the thresholds, so it reads back as unknown. (map_saver's 205
    reads back as *free* under free_thresh 0.25: 50/255 = 0.196.) ``scale``:
    ``p = round(255 * (1 - risk))``; never-observed cells are transparent (map_server's only
    unknown in scale mode). ``raw``: ``p`` is the cell's ``probability`` value 0..100, unknown
    255 (map_server copies 0..100 and reads anything else as -1).
    """
    if mode == "trinary":
        unknown_grey = round(255.0 * (1.0 - 0.5 * (free_thresh + occupied_thresh)))
        grey = np.full(risk.shape, unknown_grey, dtype=np.uint8)
        grey[(risk > occupied_thresh) & observed] = 0  # occ 1: occupied under any occupied_thresh <= 1
        grey[(risk < free_thresh) & observed] = 255  # occ 0: free under any free_thresh >= 0
    elif mode == "raw":
        grey = np.rint(np.clip(risk, 0.0, 1.0) * 100.0).astype(np.uint8)
        grey[~observed] = RAW_UNKNOWN_PIXEL
    else:
        grey = _scale_grey(np.where(observed, risk, np.float32(0.5)))
    return _image_rows(grey), _image_rows(observed)


def pgm_bytes(grey: np.ndarray) -> bytes:
    """Binary PGM (P5, maxval 255) of image rows."""
    height, width = grey.shape
    return f"P5\n# fuzzyrisk\n{width} {height}\n255\n".encode("ascii") + grey.astype(np.uint8).tobytes()


def nav2_zip(
    risk: np.ndarray,
    observed: np.ndarray,
    *,
    resolution: float,
    origin_xy: tuple[float, float],
    mode: Nav2Mode = "trinary",
    image_format: Literal["pgm", "png"] = "pgm",
    free_thresh: float = NAV2_FREE_THRESH,
    occupied_thresh: float = NAV2_OCCUPIED_THRESH,
    frame_id: str | None = None,
    date_time: tuple[int, int, int, int, int, int] | None = None,
) -> bytes:
    """A zip of ``map.yaml`` and ``map.pgm`` (or ``map.png``) that Nav2's map_server loads as is.

    map_server publishes ``occupancy_data`` of the same mode (``probability`` for ``raw``), unknown
    included. ValueError for thresholds ``check_thresholds`` refuses and for ``scale`` as PGM.
    ``frame_id``: written as a comment in ``map.yaml`` (map_server's YAML has no frame; its
    ``frame_id`` parameter sets it). ``date_time``: the entries' date (default: now), so that one
    map version can give the same bytes every time.
    """
    check_thresholds(free_thresh, occupied_thresh)
    check_nav2_format(mode, image_format)
    grey, opaque = nav2_pixels(risk, observed, mode=mode, free_thresh=free_thresh, occupied_thresh=occupied_thresh)
    image_name = f"map.{image_format}"
    if image_format == "pgm":
        image = pgm_bytes(grey)
    else:
        out = io.BytesIO()
        if mode == "scale":
            alpha = np.where(opaque, 255, 0).astype(np.uint8)
            Image.fromarray(np.stack([grey, alpha], axis=2), mode="LA").save(out, format="PNG")
        else:
            # trinary and raw PNGs without alpha: Jazzy's map_server reads any alpha below 255 as
            # unknown in trinary mode too, older releases average it into the grey; raw ignores it
            Image.fromarray(grey, mode="L").save(out, format="PNG")
        image = out.getvalue()
    meta = {
        "image": image_name,
        "mode": mode,
        "resolution": float(resolution),
        "origin": [float(origin_xy[0]), float(origin_xy[1]), 0.0],
        "negate": 0,
        "occupied_thresh": float(occupied_thresh),
        "free_thresh": float(free_thresh),
    }
    yaml_text = yaml.safe_dump(meta, sort_keys=False, default_flow_style=None)
    if frame_id is not None:
        yaml_text = f"# frame: {frame_id} (set map_server's frame_id parameter to it)\n{yaml_text}"
    stamp = date_time or time.localtime()[:6]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, content in (("map.yaml", yaml_text.encode()), (image_name, image)):
            entry = zipfile.ZipInfo(name, date_time=stamp)
            entry.compress_type = zipfile.ZIP_DEFLATED
            # rw-r--r--: map_server often runs as another user than the one who unzips
            entry.external_attr = (0o100644 & 0xFFFF) << 16
            archive.writestr(entry, content)
    return buffer.getvalue()


#: ``int8_json_array``'s text of each value from -1 to 100, right-aligned in 4 bytes with its comma.
_INT8_TEXT = np.frombuffer(b"".join(f"{v:>3},".encode() for v in range(-1, 101)), dtype=np.uint8).reshape(-1, 4)


def int8_json_array(data: np.ndarray) -> bytes:
    """``data`` (values in -1..100, an OccupancyGrid's) as a JSON array, built by numpy without a Python loop.

    Each value takes 4 bytes (the padding is JSON whitespace): 16 M cells in a fraction of a second
    with the GIL mostly free, where pydantic held it for 2-3 s and every request waited.
    """
    flat = np.asarray(data, dtype=np.int16).reshape(-1)
    if flat.size == 0:
        return b"[]"
    if flat.min() < -1 or flat.max() > 100:
        raise ValueError("OccupancyGrid data must lie in -1..100")
    text = _INT8_TEXT[flat + 1].reshape(-1).tobytes()
    return b"[" + text[:-1] + b"]"
