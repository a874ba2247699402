"""Reads of a map: its grid at one version, and every representation made of it (JSON, .npy, PNG, map_server,
OccupancyGrid, MCAP); copies under the map's apply lock, encodings in the read threads."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import math
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from typing import Any, Literal, TypeVar

import numpy as np

from app.scans import scan_view
from app.formats import etags
from app.formats import exports
from app.ros import messages_out
from app.ros import msgtypes
from app.config import Settings
from app.errors import Conflict, Invalid, NotFound, TooLarge, Unavailable
from app.maps import GridSnapshot, GridStamp, MapEntry, copy_limit, history_of
from app.reads import trajectory
from app.reads.lane import ReadLane, Turn
from app.schemas import WHOLE_MAP, GridWindow, LastScan, MapInfo, OccupancyGrid, RiskGridJSON, RiskValues
from app.storage import Storage, StoredMap
from app.ops.threads import Workers
from fuzzyocc import GridSpec
from fuzzyocc.maps import Window

LOG = logging.getLogger("fuzzyrisk.maps")
T = TypeVar("T")

#: Above this many cells the JSON risk grid is refused (use format=npy or png).
MAX_JSON_CELLS = 4_000_000
#: Reads of maps with more cells take turns in the big reads' lane (``app.reads.lane``), in a thread of their own
#: (``Workers.run_read(heavy=True)``): two readers of a 16 M-cell map's OccupancyGrid (16 MB of CDR, about 0.3 s
#: each) held both read threads, and another map's 176,000-cell reads waited (bench abuse row 10:
#: p99 13 -> 232 ms)
HEAVY_READ_CELLS = 4_000_000
#: Most pixels of one PNG.
MAX_PNG_PIXELS = 64_000_000


class MapReads:
    """A map's outputs, each consistent with one version of the map."""

    def __init__(self, settings: Settings, storage: Storage, workers: Workers,
                 current: Callable[[str], Awaitable[MapEntry]]) -> None:
        self.settings = settings
        self.storage = storage
        self._workers = workers
        self._current = current  # ``WritePath.current``: the map with every acknowledged batch applied
        self._lane = ReadLane(share=settings.heavy_read_share, queue=settings.heavy_read_queue)

    @contextlib.asynccontextmanager
    async def big_read(self, spec: GridSpec | Window) -> AsyncIterator[Turn | None]:
        """A turn in the big reads' lane for a read of more than ``HEAVY_READ_CELLS`` cells (its copy, its render
        and, handed over to the response, the sending of its body; or a plan's copy and publication); None for a
        smaller read."""
        if _heavy(spec):
            async with self._lane.turn() as turn:
                yield turn
        else:
            yield None

    async def map_info(self, name: str) -> MapInfo:
        """What ``GET /maps/{name}`` shows."""
        entry = await self._current(name)
        head = await self._workers.run_read(self.storage.map_head, name)  # the history as stored (one indexed row)
        return entry.info(history_of(head))

    async def last_scan(self, name: str) -> LastScan:
        """Beam ends of the last scan fused; the view is built at the first request, not per batch."""
        entry = await self._current(name)
        scan, view, version = entry.last_scan, entry.last_view, entry.version
        if scan is None:
            raise NotFound(f"map {name!r} has fused no scan since the service started")
        if view is None:
            # most batches are never drawn; a big cloud's view takes a while, so off the event loop
            view = await self._workers.run_read(scan_view, scan)
            if entry.last_scan is scan:  # not replaced by a newer batch meanwhile
                entry.last_view = view
        return LastScan(origin=view.origin, endpoints=view.endpoints, hit=view.hit, version=version)

    # ---------------------------------------------------------------- risk

    async def current_etag(self, name: str, variant: Mapping[str, Any]) -> tuple[str, int]:
        """The ETag a read of ``variant`` would carry now, and the version (no grid read: for If-None-Match)."""
        entry = await self._current(name)
        return etags.entity_tag(entry.etag_seed, entry.version, variant), entry.version

    async def read_grid(self, name: str, region: GridWindow = WHOLE_MAP) -> GridSnapshot:
        """The map's risk and observed arrays over ``region``, consistent with one version.

        ``risk()`` and ``observed()`` already hand out new read-only arrays, so no copy is needed.
        """
        entry = await self._current(name)
        async with self.big_read(await self._planned(entry, region)):
            return await self.read_grid_of(entry, region)

    async def read_grid_of(self, entry: MapEntry, region: GridWindow = WHOLE_MAP) -> GridSnapshot:
        """``read_grid`` of a map already looked up; a caller of a big read holds its ``big_read`` turn.

        Only the window's cells are copied, under the apply lock: the cost follows the window, not the map.
        """
        async with entry.apply_lock:
            window = await self._resolved(entry, region)
            risk, observed = await self._workers.run_read(
                lambda: (entry.map.risk(window), entry.map.observed(window)), heavy=_heavy(window))
            # version and updated are assigned together under this lock (``_write``): they match the arrays
            return GridSnapshot(_spec_of(entry, window), entry.version, risk, observed, entry.frame_id,
                                entry.updated, entry.etag_seed)

    async def read_cells(self, entry: MapEntry, window: Window) -> GridSnapshot:
        """The map's grid over ``window`` as given (a growing map's plan reaches past its bounds: never observed
        there), at one version; a caller of a big read holds its ``big_read`` turn."""
        async with entry.apply_lock:
            risk, observed = await self._workers.run_read(
                lambda: (entry.map.risk(window), entry.map.observed(window)), heavy=_heavy(window))
            return GridSnapshot(window.spec(), entry.version, risk, observed, entry.frame_id, entry.updated,
                                entry.etag_seed)

    async def computed(self, name: str, compute: Callable[[GridSnapshot], T]) -> T:
        """``compute(grid)`` in a read thread, on the map's grid at one version (a big map's in its turn in the lane):
        what is worked out from a grid and answered small, a path check."""
        entry = await self._current(name)
        async with self.big_read(await self._planned(entry, WHOLE_MAP)):
            grid = await self.read_grid_of(entry)
            return await self._workers.run_read(compute, grid, heavy=_heavy(grid.spec))

    async def _planned(self, entry: MapEntry, region: GridWindow) -> Window:
        """The cells a read of ``region`` would cover now, for its limits and its lane, before any copy: a fixed
        map's from its box alone; a growing map's from its bounds under the apply lock (they may grow before
        the copy, which reads them again)."""
        if not entry.map.growing:
            return _window(entry, region)
        async with entry.apply_lock:
            return await self._resolved(entry, region)

    async def _resolved(self, entry: MapEntry, region: GridWindow) -> Window:
        """``_window`` under the apply lock (a growing map's bounds are read from its blocks: in a read thread).

        A growing map's window is bounded as a fixed map's box is (``copy_limit``), before any copy: two scans far
        apart give bounds of more cells than any memory holds."""
        if not entry.map.growing:
            return _window(entry, region)
        window = await self._workers.run_read(_window, entry, region)
        limit = copy_limit(self.settings)
        if window.cells() > limit:
            raise Invalid(f"the read covers {window.cells():,} cells ({' x '.join(map(str, window.shape))}) of this "
                          f"growing map, more than a fixed map's largest box ({limit:,}: FUZZYRISK_MAX_MAP_CELLS or "
                          "64 M, the larger): read a window of it (min, max)")
        return window

    async def render_log(self, name: str, render: Callable[[GridSnapshot, StoredMap], T],
                         region: GridWindow = WHOLE_MAP) -> T:
        """``render(grid, stored)`` in a read thread: the map's grid over ``region`` and its stored batch log at one
        version (``_with_log``; ``app.reads.recording``)."""
        entry = await self._current(name)

        async def copy(held: MapEntry) -> GridSnapshot:
            window = await self._resolved(held, region)
            risk, observed = await self._workers.run_read(
                lambda e=held, w=window: (e.map.risk(w), e.map.observed(w)), heavy=_heavy(window))
            return GridSnapshot(_spec_of(held, window), held.version, risk, observed, held.frame_id, held.updated,
                                held.etag_seed)

        async with self.big_read(await self._planned(entry, region)):
            grid, stored = await self._with_log(name, entry, copy, self.storage.load_map)
            return await self._workers.run_read(render, grid, stored, heavy=_heavy(grid.spec))

    async def trajectory(self, name: str) -> tuple[bytes, int]:
        """The map's trajectory as ``Trajectory`` JSON (``app.reads.trajectory``), and the version it is of: the scans
        of its whole history (``Storage.load_history``: every batch after its base snapshot)."""

        async def copy(held: MapEntry) -> tuple[int, str, str]:
            return held.version, held.frame_id, held.updated

        (version, frame_id, updated), stored = await self._with_log(name, await self._current(name), copy,
                                                                    self.storage.load_history)
        made = await self._workers.run_read(functools.partial(
            trajectory.trajectory_json, stored.batches, moved=stored.poses, frame_id=frame_id, stamp=msgtypes.ros_time_of_iso(updated),
            version=version, from_version=stored.snapshot_version, max_poses=self.settings.max_trajectory_poses),
            heavy=True)
        return made, version

    async def _with_log(self, name: str, entry: MapEntry, copy: Callable[[MapEntry], Awaitable[T]],
                        load: Callable[[str], StoredMap | None]) -> tuple[T, StoredMap]:
        """``copy(entry)`` and the map's stored batches at one version, as ``load`` reads them (``Storage.load_map``:
        the batches after the restart snapshot; ``Storage.load_history``: after the base), ``stored.snapshot``
        dropped.

        Both are taken together under the apply lock, so no batch is applied between the two: the log
        holds every batch up to the copy's version (each was committed before it was applied), and those
        committed but not applied yet are left out.
        """
        for attempt in range(3):
            if attempt:
                entry = await self._current(name)
            async with entry.apply_lock:
                copied, version = await copy(entry), entry.version
                stored = await self._workers.run_read(load, entry.name)
            # another replica's snapshot newer than this version: the log read starts after it; catch up, again
            if stored is None or stored.snapshot_version <= version:
                break
        if stored is None or stored.incarnation != entry.incarnation \
                or stored.meta.get("created") != entry.meta["created"]:  # deleted (and made again)
            raise NotFound(f"no map named {name!r}; GET /maps lists them")
        if stored.snapshot_version > version:
            raise Unavailable(f"map {name!r} changes faster than its log can be read; retry",
                              headers={"Retry-After": "1"})
        if stored.damage:
            raise Unavailable(f"map {name!r}: its stored log is damaged ({'; '.join(stored.damage)})")
        stored.snapshot = None
        stored.batches = [(v, payload) for v, payload in stored.batches if v <= version]
        return copied, stored

    async def risk_at(self, name: str, points: list[list[float]]) -> RiskValues:
        if len(points) > self.settings.max_query_points:
            raise TooLarge(
                f"{len(points)} points, more than the limit of {self.settings.max_query_points} "
                "(FUZZYRISK_MAX_QUERY_POINTS): split the query"
            )
        entry = await self._current(name)
        dims = entry.spec.ndim
        if any(len(p) != dims for p in points):
            bad = next(i for i, p in enumerate(points) if len(p) != dims)
            raise Invalid(f"points[{bad}] has {len(points[bad])} coordinates; this map is {dims}-D")
        async with entry.apply_lock:
            try:
                values = await self._workers.run_read(entry.map.risk_at, np.asarray(points, dtype=np.float64))
            except ValueError as exc:
                raise Invalid(str(exc)) from None
            return RiskValues(risk=[float(v) for v in values], version=entry.version)

    async def risk_json(self, name: str, region: GridWindow = WHOLE_MAP) -> tuple[bytes, GridSnapshot]:
        """The grid as ``RiskGridJSON``, serialised (off the event loop: big maps make big documents)."""
        entry = await self._current(name)
        cells = _cells(await self._planned(entry, region))
        if cells > MAX_JSON_CELLS:
            raise Invalid(
                f"the read has {cells} cells, too many for JSON (at most {MAX_JSON_CELLS}); "
                "ask for format=npy or format=png, or a smaller window (min, max)"
            )
        grid = await self.read_grid_of(entry, region)  # not a big read: no turn in the lane

        def encode() -> bytes:
            return RiskGridJSON(
                name=name, version=grid.version, frame_id=grid.frame_id, resolution=grid.spec.resolution,
                origin=list(grid.spec.origin), shape=list(grid.spec.shape),
                risk=np.round(grid.risk.astype(np.float64), 6).tolist(), observed=grid.observed.tolist(),
            ).model_dump_json().encode()

        return await self._workers.run_read(encode, heavy=_heavy(grid.spec)), grid

    async def _rendered(self, entry: MapEntry, render: Callable[[GridSnapshot], T], region: GridWindow,
                        planned: Window | None = None) -> tuple[T, GridSnapshot, Sent]:
        """``render(grid)`` of the map's grid over ``region`` at one version, in a read thread: for a big read in its
        turn in the lane, handed over to the response (``Sent``). ``planned``: ``_planned``, if already known."""
        planned = await self._planned(entry, region) if planned is None else planned
        async with self.big_read(planned) as turn:
            grid = await self.read_grid_of(entry, region)
            return await self._workers.run_read(render, grid, heavy=_heavy(grid.spec)), grid, _hand_over(turn)

    async def risk_npy(self, name: str, layer: Literal["risk", "observed"] = "risk",
                       region: GridWindow = WHOLE_MAP) -> tuple[bytes, GridSnapshot, Sent]:
        """The risk (float32) or the observed mask (bool) as ``.npy``, of one version (and ``Sent``)."""
        return await self._rendered(await self._current(name),
                                    lambda grid: exports.npy_bytes(grid.risk if layer == "risk" else grid.observed),
                                    region)

    async def risk_png(self, name: str, *, scale: int, z_min: float | None, z_max: float | None,
                       region: GridWindow = WHOLE_MAP) -> tuple[bytes, GridSnapshot, Sent]:
        _check_band(z_min, z_max)
        entry = await self._current(name)
        planned = await self._planned(entry, region)
        nx, ny = planned.shape[:2]
        if nx * ny * scale * scale > MAX_PNG_PIXELS:
            raise Invalid(f"scale {scale} would make a {nx * scale} x {ny * scale} image; use a smaller scale or "
                          "window (min, max)")

        def render(grid: GridSnapshot) -> bytes:
            text = {
                "map": name, "version": str(grid.version), "frame_id": grid.frame_id,
                "resolution": repr(grid.spec.resolution), "origin": repr(list(grid.spec.origin)),
            }
            risk, observed = grid.planar(z_min, z_max)
            return exports.risk_png(risk, observed, scale=scale, text=text)

        return await self._rendered(entry, render, region, planned)

    async def nav2_zip(
        self, name: str, *, mode: Literal["trinary", "scale", "raw"], image_format: Literal["pgm", "png"],
        free_thresh: float, occupied_thresh: float, z_min: float | None, z_max: float | None,
        region: GridWindow = WHOLE_MAP,
    ) -> tuple[bytes, GridSnapshot, Sent]:
        """The zip for map_server; its entries are dated by the map's last batch, so one version gives one file."""
        _check_band(z_min, z_max)
        _check_thresholds(free_thresh, occupied_thresh)
        try:
            exports.check_nav2_format(mode, image_format)
        except ValueError as exc:
            raise Invalid(str(exc)) from None

        def render(grid: GridSnapshot) -> bytes:
            risk, observed = grid.planar(z_min, z_max)
            return exports.nav2_zip(
                risk, observed, resolution=grid.spec.resolution, origin_xy=grid.spec.origin[:2], mode=mode,
                image_format=image_format, free_thresh=free_thresh, occupied_thresh=occupied_thresh,
                frame_id=grid.frame_id, date_time=messages_out.zip_date_time(grid.updated),
            )

        return await self._rendered(await self._current(name), render, region)

    async def occupancy_grid(
        self, name: str, *, mode: Literal["trinary", "scale", "probability"], free_thresh: float,
        occupied_thresh: float, z_min: float | None, z_max: float | None,
        encoding: Literal["json", "cdr", "mcap"] = "json", region: GridWindow = WHOLE_MAP,
    ) -> tuple[bytes | tuple[bytes, memoryview], GridStamp, Sent]:
        """The map as a ``nav_msgs/OccupancyGrid``: JSON (``OccupancyGrid``), CDR bytes, or an MCAP file.

        The stamp and ``map_load_time`` are when the map reached this version (``GridSnapshot.updated``),
        so every read of one version gives the same bytes. JSON is refused above ``MAX_JSON_CELLS`` cells, as
        the risk grid's: 16 M values written as text took 1-3 s of the GIL per read, and stalled every
        client of the service; CDR and MCAP carry them as bytes.
        """
        _check_band(z_min, z_max)
        _check_thresholds(free_thresh, occupied_thresh)
        entry = await self._current(name)
        planned = await self._planned(entry, region)
        if encoding == "json":
            cells = planned.shape[0] * planned.shape[1]  # the message is the plane, a 3-D map's included
            if cells > MAX_JSON_CELLS:
                raise Invalid(
                    f"the OccupancyGrid has {cells:,} cells, too many for JSON (at most {MAX_JSON_CELLS:,}): "
                    f"ask for GET /maps/{name}/occupancy_grid.cdr or .mcap (the same message as ROS 2 bytes), or "
                    "a smaller window (min, max)"
                )
        heavy = _heavy(planned)
        async with self.big_read(planned) as turn:
            if len(planned.shape) == 2:
                async with entry.apply_lock:
                    window = await self._resolved(entry, region)

                    # the values straight from the map's risk codes, in one pass (a 16 M-cell map: 45 ms against
                    # 160, without the 80 MB copy of its risk and observed mask)
                    def lookup() -> np.ndarray:  # the table too is built here, not on the event loop (cached)
                        return entry.map.plane_lookup(exports.occupancy_lut(mode, free_thresh, occupied_thresh), -1,
                                                      window)

                    values = await self._workers.run_read(lookup, heavy=heavy)
                    # the version the values are of: it changes under this lock only
                    stamp = dataclasses.replace(entry.stamp(), spec=_spec_of(entry, window))
            else:
                grid = await self.read_grid_of(entry, region)

                def project() -> np.ndarray:
                    risk, observed = grid.planar(z_min, z_max)
                    return exports.occupancy_data(risk, observed, mode=mode, free_thresh=free_thresh,
                                                  occupied_thresh=occupied_thresh).reshape(risk.shape[1],
                                                                                           risk.shape[0])

                values, stamp = await self._workers.run_read(project, heavy=heavy), grid.stamp()
            message = await self._workers.run_read(_occupancy_message, values, stamp, encoding, heavy=heavy)
            return message, stamp, _hand_over(turn)


#: Called once a read's body is sent (``largebody.bytes_response(on_sent=...)``): a big read's turn in the lane
#: ends then; None for a small map's read
Sent = Callable[[], None] | None


def _hand_over(turn: Turn | None) -> Sent:
    return turn.hand_over() if turn is not None else None


def _occupancy_message(values: np.ndarray, grid: GridStamp,
                       encoding: Literal["json", "cdr", "mcap"]) -> bytes | tuple[bytes, memoryview]:
    """A ``nav_msgs/OccupancyGrid`` of ``values`` ((height, width) int8, rows along y) as JSON, CDR or MCAP."""
    height, width = values.shape
    data = values.reshape(-1)
    stamp = msgtypes.ros_time_of_iso(grid.updated)
    if encoding != "json":
        message = messages_out.occupancy_grid_message(
            data, width=width, height=height, resolution=grid.spec.resolution,
            origin_xy=grid.spec.origin[:2], frame_id=grid.frame_id, stamp=stamp,
        )
        if encoding == "cdr":
            return messages_out.occupancy_grid_cdr_parts(message)
        return messages_out.occupancy_grid_mcap(messages_out.occupancy_grid_cdr(message),
                                          log_time_ns=msgtypes.ns_of_ros_time(stamp))
    # the small fields through the model (validated), the 4-16 M values by numpy: one pydantic pass over
    # them held the GIL, and so every request, for seconds
    head = OccupancyGrid.model_validate({
        "header": {"stamp": stamp, "frame_id": grid.frame_id},
        "info": {
            "map_load_time": stamp, "resolution": grid.spec.resolution,
            "width": int(width), "height": int(height),
            "origin": {"position": {"x": grid.spec.origin[0], "y": grid.spec.origin[1], "z": 0.0},
                       "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
        },
        "data": [],
        "version": grid.version,
    }).model_dump_json().encode()
    empty = b'"data":[]'
    assert head.count(empty) == 1
    return head.replace(empty, b'"data":' + exports.int8_json_array(data))


def _check_thresholds(free_thresh: float, occupied_thresh: float) -> None:
    # an 8-bit map image needs a grey strictly between the thresholds for "unknown"
    try:
        exports.check_thresholds(free_thresh, occupied_thresh)
    except ValueError as exc:
        raise Invalid(str(exc)) from None


def _check_band(z_min: float | None, z_max: float | None) -> None:
    if z_min is not None and z_max is not None and z_min > z_max:
        raise Invalid(f"z_min ({z_min}) must not exceed z_max ({z_max})")


def _window(entry: MapEntry, region: GridWindow) -> Window:
    """The cells a read of ``region`` covers (a growing map's: call under its apply lock; a fixed map's box alone
    says). ``Invalid`` naming min or max when a corner does not fit the map or nothing is left."""
    dims = entry.map.lattice.ndim
    for field, corner in (("min", region.min), ("max", region.max)):
        if corner is not None and len(corner) != dims:
            raise Invalid(f"{field} has {len(corner)} coordinates; this map is {dims}-D: give {dims}")
    if region.min is not None and region.max is not None:
        for axis, (low, high) in enumerate(zip(region.min, region.max)):
            if low > high:
                raise Invalid(f"min ({low}) exceeds max ({high}) along {'xyz'[axis]}: the window is empty")
    window = entry.map.window(region.min, region.max)
    if window is not None:
        return window
    whole = entry.map.window()
    if whole is None:
        raise Conflict(f"map {entry.name!r} is a growing map that has observed nothing yet: it has no grid to read "
                       "until the first scan reaches a cell (its bounds are null)")
    raise Invalid(f"the window min={_corner(region.min)}, max={_corner(region.max)} meets no cell of the map, "
                  f"which covers {_corner(whole.origin)} to {_corner(whole.upper)}")


def _corner(corner: tuple[float, ...] | None) -> str:
    return "(none)" if corner is None else ",".join(repr(v) for v in corner)


def _spec_of(entry: MapEntry, window: Window) -> GridSpec:
    """The spec a read of ``window`` states: the map's own for a fixed map's whole box (its origin as made, the
    bytes of a read before windows), else the window's."""
    spec = entry.spec
    if isinstance(spec, GridSpec) and window.shape == spec.shape and not any(window.lo):
        return spec
    return window.spec()


def _cells(window: GridSpec | Window) -> int:
    return math.prod(window.shape)


def _heavy(window: GridSpec | Window) -> bool:
    return _cells(window) > HEAVY_READ_CELLS
