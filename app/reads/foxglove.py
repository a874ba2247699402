"""Live view in Foxglove: a Foxglove WebSocket server showing each map's grid, last scan and plans.

Off unless ``FUZZYRISK_FOXGLOVE_PORT`` is set; this module (and the ``foxglove-sdk`` package, the
``foxglove`` extra) is imported only then. Open Foxglove, connect to ``ws://HOST:PORT`` and add
a 3D panel: per map ``NAME`` there are

* ``/fuzzyrisk/NAME/grid`` (``foxglove.Grid``): the risk as float32 (``risk``, exactly the map's,
  the max-risk projection of a 3-D map) and, per cell, the operator page's colours (``red``,
  ``green``, ``blue``, ``alpha``: white free to dark crimson occupied, grey-blue never observed),
  which the 3D panel shows as they are; "Color by risk" switches to a colour map of the values;
* ``/fuzzyrisk/NAME/scan`` (``foxglove.LaserScan``, the last LaserScan at its pose) or
  ``/fuzzyrisk/NAME/cloud`` (``foxglove.PointCloud``, the last point cloud in the map frame);
* ``/fuzzyrisk/NAME/plan`` (``foxglove.SceneUpdate``): the last plan's path as a line.

Why Foxglove's own schemas rather than ROS 2's: ``nav_msgs/OccupancyGrid`` holds int8 0..100, so
it would show the risk rounded to hundredths with Foxglove's map palette, where ``foxglove.Grid``
carries the float32 risk itself and the page's colours; ``foxglove.LaserScan`` carries its pose,
so a scan needs no TF tree; ``nav_msgs/Path`` is drawn as arrows or a line depending on settings,
a SceneUpdate line is drawn as a line.

Every message of a map is in the map's frame (``frame_id``, ``map`` unless the map was created
with another): the service gives it with each change, and the slots of the maps there at start
take it from their ``MapInfo``.

What the view costs the service: the service tells this module what changed (``MapObserver``, on
the event loop, O(1)): each map has a latest-value slot, drained by one publisher thread at most
once per ``FUZZYRISK_FOXGLOVE_INTERVAL_S`` per map. The thread reads the grid as any reader does
(``MapReads.read_grid``: ``risk()`` and ``observed()`` copied under the map's apply lock, between
two batches), only when a client is subscribed to the grid, so a batch of that map may wait for
one such copy per interval (docs/DESIGN.md 8.2 has the figure); everything else (the projection
of a 3-D map, the downsampling, the colours, the encoding) happens after, in the publisher
thread. A grid is published with at most ``FUZZYRISK_FOXGLOVE_MAX_CELLS`` cells: a larger map
is shown in blocks of k x k cells (k the smallest integer that fits), each the largest risk of its
observed cells, so an obstacle never vanishes from the view. A client that subscribes gets the
latest grid, scan and plan at once.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.formats import exports
from app.ops.process_setup import StartupError, foxglove_sdk_missing
from app.schemas import DEFAULT_FRAME_ID, PlanResult
from fuzzyocc import scans as fuzzy_scans

try:
    import foxglove
    from foxglove.channels import GridChannel, LaserScanChannel, PointCloudChannel, SceneUpdateChannel
    from foxglove.messages import (
        Color,
        Grid,
        LaserScan,
        LinePrimitive,
        PackedElementField,
        PackedElementFieldNumericType,
        Point3,
        PointCloud,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        Timestamp,
        Vector2,
        Vector3,
    )
except ImportError as exc:  # the optional extra is not installed
    raise foxglove_sdk_missing(exc) from None

LOG = logging.getLogger("fuzzyrisk.foxglove")
TOPIC_PREFIX = "/fuzzyrisk/"
#: Most points of a published point cloud (evenly thinned beyond): a view, not the data.
MAX_CLOUD_POINTS = 200_000
#: What a slow client's queue may hold, about: the SDK bounds it in messages only
#: (``message_backlog_size``; beyond, the client's oldest data message goes, and a newer grid
#: follows), so the count is this budget over the largest message (``client_backlog``).
CLIENT_BACKLOG_BYTES = 64 * 2**20
#: Fewest and most messages a client's queue holds. The SDK gives its control queue (channels
#: advertised and withdrawn) the same size and disconnects a client that fills it: not too few.
MIN_CLIENT_BACKLOG, MAX_CLIENT_BACKLOG = 4, 16
#: Seconds the publisher waits for a grid read before giving that publication up.
READ_TIMEOUT_S = 60.0
_F32, _U8 = PackedElementFieldNumericType.Float32, PackedElementFieldNumericType.Uint8
#: One grid cell: the risk, then the page's colour (Foxglove shows red/green/blue/alpha fields as colours).
GRID_CELL = np.dtype([("risk", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])
GRID_FIELDS = [PackedElementField(name="risk", offset=0, type=_F32)] + [
    PackedElementField(name=name, offset=4 + i, type=_U8) for i, name in enumerate(("red", "green", "blue", "alpha"))
]
CLOUD_FIELDS = [PackedElementField(name=axis, offset=4 * i, type=_F32) for i, axis in enumerate("xyz")]
PLAN_COLOURS = {"exact": Color(r=0.1, g=0.45, b=0.9, a=1.0), "approximate": Color(r=0.95, g=0.55, b=0.1, a=1.0)}

#: ``read_grid(name)``: the map's ``GridSnapshot`` (``app.service.mapservice``), from the publisher thread.
ReadGrid = Callable[[str], Any]


def topic(name: str, what: str) -> str:
    return f"{TOPIC_PREFIX}{name}/{what}"


@dataclass
class _Slot:
    """What one map has to publish: the latest of each kind, and its channels (publisher thread only)."""

    grid_due: bool = False
    scan: Any = None  # fuzzyocc LaserScan or PointCloud
    scan_due: bool = False
    plan: PlanResult | None = None
    plan_due: bool = False
    deleted: bool = False
    published_at: float = -math.inf
    frame_id: str = DEFAULT_FRAME_ID  # the map's (MapInfo at start, then each change says it)
    channels: dict[str, Any] = field(default_factory=dict)


class LiveView:
    """The Foxglove server and its publisher thread; a ``MapObserver`` of the service (``app.service.mapservice``)."""

    def __init__(self, *, host: str, port: int, interval_s: float, read_grid: ReadGrid,
                 max_cells: int = 1_000_000) -> None:
        self._host, self._port, self._interval_s = host, port, interval_s
        self._read_grid = read_grid
        self._max_cells = max_cells
        self._context = foxglove.Context()  # ours alone: no other code's channels reach this server
        self._slots: dict[str, _Slot] = {}
        self._cond = threading.Condition()
        self._stopping = False
        self._server: Any = None
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------ lifecycle

    def start(self, frames: dict[str, str]) -> int:
        """Listen, publish the maps ``frames`` (name -> frame_id) and start publishing; the port listened on."""
        try:
            self._server = foxglove.start_server(
                name="fuzzyrisk", host=self._host, port=self._port, context=self._context, server_listener=self,
                message_backlog_size=client_backlog(self._max_cells),
            )
        except Exception as exc:  # noqa: BLE001 - the SDK's error types are its own; the message says it
            raise StartupError(f"the Foxglove live view cannot listen on {self._host}:{self._port} ({exc}): choose "
                               "another FUZZYRISK_FOXGLOVE_PORT, or unset it") from None
        with self._cond:
            for name, frame_id in frames.items():
                self._slots[name] = _Slot(grid_due=True, frame_id=frame_id)
        self._thread = threading.Thread(target=self._run, name="foxglove-live", daemon=True)
        self._thread.start()
        LOG.info("Foxglove live view listening", extra={"fields": {"url": f"ws://{self._host}:{self._server.port}"}})
        return int(self._server.port)

    def close(self) -> None:
        """Stop publishing (the thread ends after its current message) and close the server."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(READ_TIMEOUT_S + 5.0)
        if self._server is not None:
            self._server.stop()

    # ------------------------------------------------------------ MapObserver: on the event loop, O(1)

    def batch_applied(self, name: str, version: int, last_scan: Any, frame_id: str) -> None:
        with self._cond:
            slot = self._slots.setdefault(name, _Slot())
            slot.frame_id = frame_id
            slot.grid_due, slot.scan, slot.scan_due = True, last_scan, True
            self._cond.notify_all()

    def plan_made(self, name: str, result: PlanResult, frame_id: str) -> None:
        with self._cond:
            slot = self._slots.setdefault(name, _Slot())
            slot.frame_id = frame_id
            slot.plan, slot.plan_due = result, True
            self._cond.notify_all()

    def map_deleted(self, name: str) -> None:
        with self._cond:
            slot = self._slots.get(name)
            if slot is not None:
                slot.deleted = True
                self._cond.notify_all()

    # ------------------------------------------------------------ foxglove ServerListener (SDK threads)

    def on_subscribe(self, client: Any, channel: Any) -> None:
        """A new viewer: send the map's latest grid, scan and plan again (the server keeps no history)."""
        try:
            name = str(channel.topic).removeprefix(TOPIC_PREFIX).rsplit("/", 1)[0]
            with self._cond:
                slot = self._slots.get(name)
                if slot is not None:
                    slot.grid_due, slot.scan_due, slot.plan_due = True, slot.scan is not None, slot.plan is not None
                    slot.published_at = -math.inf  # at once, not after the interval
                    self._cond.notify_all()
        except Exception:
            LOG.exception("Foxglove subscription not handled")

    # ------------------------------------------------------------ the publisher thread

    def _run(self) -> None:
        while True:
            with self._cond:
                work = self._next_due()
                while work is None and not self._stopping:
                    self._cond.wait(self._wait_s())
                    work = self._next_due()
                if self._stopping:
                    return
            name, slot, frame_id, grid, scan, plan, deleted = work
            try:
                self._publish(name, slot, frame_id, grid=grid, scan=scan, plan=plan, deleted=deleted)
            except Exception:
                LOG.exception("Foxglove publication failed", extra={"fields": {"map": name}})

    def _next_due(self) -> tuple[str, _Slot, str, bool, Any, PlanResult | None, bool] | None:
        """The first map with something due, its frame, its due flags taken (caller holds the lock)."""
        now = time.monotonic()
        for name, slot in self._slots.items():
            grid = slot.grid_due and now - slot.published_at >= self._interval_s
            if slot.deleted or grid or slot.scan_due or slot.plan_due:
                if slot.deleted:
                    del self._slots[name]
                    return name, slot, slot.frame_id, False, None, None, True
                scan = slot.scan if (slot.scan_due and (grid or not slot.grid_due)) else None
                plan = slot.plan if slot.plan_due else None
                if not (grid or scan is not None or plan is not None):
                    continue  # a scan waits for its grid: the two are shown together
                slot.grid_due &= not grid
                slot.scan_due &= scan is None
                slot.plan_due = False
                if grid:
                    slot.published_at = now
                return name, slot, slot.frame_id, grid, scan, plan, False
        return None

    def _wait_s(self) -> float | None:
        """Until the next grid falls due (None: until notified)."""
        pending = [slot.published_at + self._interval_s for slot in self._slots.values() if slot.grid_due]
        return max(0.0, min(pending) - time.monotonic()) if pending else None

    def _channel(self, slot: _Slot, name: str, kind: str, make: Callable[..., Any]) -> Any:
        channel = slot.channels.get(kind)
        if channel is None:
            channel = slot.channels[kind] = make(topic(name, kind), context=self._context)
        return channel

    def _publish(self, name: str, slot: _Slot, frame_id: str, *, grid: bool, scan: Any, plan: PlanResult | None,
                 deleted: bool) -> None:
        if deleted:
            for channel in slot.channels.values():
                channel.close()  # unadvertised: the map is gone
            return
        grid_channel = self._channel(slot, name, "grid", GridChannel)
        if grid and grid_channel.has_sinks():  # nobody watching: no copy of the map is made
            try:
                snapshot = self._read_grid(name)
            except Exception as exc:  # noqa: BLE001 - a map deleted meanwhile, or the service stopping
                LOG.debug("grid not published: %s", exc)
                return
            grid_channel.log(grid_message(snapshot, snapshot.frame_id, max_cells=self._max_cells))
        if scan is not None:
            if isinstance(scan, fuzzy_scans.LaserScan):
                self._channel(slot, name, "scan", LaserScanChannel).log(laser_message(scan, frame_id))
            else:
                self._channel(slot, name, "cloud", PointCloudChannel).log(cloud_message(scan, frame_id))
        if plan is not None:
            self._channel(slot, name, "plan", SceneUpdateChannel).log(plan_message(plan, frame_id))


# ---------------------------------------------------------------- messages


def _now() -> Timestamp:
    return Timestamp.from_epoch_secs(time.time())


def _pose(x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z),
                orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))


def grid_cells(risk: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """(ny, nx) ``GRID_CELL`` rows (row-major along y, as foxglove.Grid wants) of a 2-D (nx, ny) map."""
    risk_yx, observed_yx = risk.T, observed.T
    cells = np.empty(risk_yx.shape, dtype=GRID_CELL)
    cells["risk"] = risk_yx
    rgb = exports.RISK_LUT[np.rint(np.clip(risk_yx, 0.0, 1.0) * 255.0).astype(np.uint8)]
    rgb[~observed_yx] = exports.UNKNOWN_RGB
    cells["red"], cells["green"], cells["blue"] = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    cells["alpha"] = 255
    return cells


def block_factor(shape: tuple[int, int], max_cells: int) -> int:
    """The smallest k whose k x k blocks of a ``shape`` grid (partial blocks at the far edges) number ``max_cells`` at most."""
    nx, ny = shape
    k = max(1, math.ceil(math.sqrt(nx * ny / max_cells)))
    while math.ceil(nx / k) * math.ceil(ny / k) > max_cells:
        k += 1
    return k


def max_blocks(risk: np.ndarray, observed: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """A 2-D (nx, ny) grid in k x k blocks: the largest risk of each block's observed cells, observed if one is.

    A block with no observed cell is unknown (risk 0.5, not observed), as a column is in
    ``exports.project_z``; the blocks at the far edges hold what is left of the map (partial blocks).
    """
    if k == 1:
        return risk, observed
    nx, ny = risk.shape
    bx, by = math.ceil(nx / k), math.ceil(ny / k)
    values = np.full((bx * k, by * k), np.float32(-1.0), dtype=np.float32)  # -1: no observed cell
    np.copyto(values[:nx, :ny], risk, where=observed)
    blocks = values.reshape(bx, k, by, k).max(axis=3).max(axis=1)
    seen = blocks >= 0.0
    return np.where(seen, blocks, np.float32(0.5)), seen


def grid_message(snapshot: Any, frame_id: str = DEFAULT_FRAME_ID, *, max_cells: int | None = None) -> Grid:
    """A ``GridSnapshot`` as a foxglove.Grid: cell (0, 0) at the map's origin corner, x along columns.

    At most ``max_cells`` cells (None: no limit): a larger map goes in blocks (``max_blocks``), its
    cells ``k`` times the map's resolution.
    """
    risk, observed = snapshot.planar(None, None)  # a 3-D map: its max-risk projection, as the page shows
    k = 1 if max_cells is None else block_factor(risk.shape, max_cells)
    risk, observed = max_blocks(risk, observed, k)
    cells = grid_cells(risk, observed)
    spec = snapshot.spec
    return Grid(
        timestamp=_now(), frame_id=frame_id, pose=_pose(spec.origin[0], spec.origin[1]),
        column_count=int(risk.shape[0]), cell_size=Vector2(x=spec.resolution * k, y=spec.resolution * k),
        row_stride=GRID_CELL.itemsize * int(risk.shape[0]), cell_stride=GRID_CELL.itemsize, fields=GRID_FIELDS,
        data=cells.tobytes(),
    )


def laser_message(scan: Any, frame_id: str = DEFAULT_FRAME_ID) -> LaserScan:
    """A fuzzyocc LaserScan at its pose (no-returns stay +inf: Foxglove draws no point for them)."""
    x, y, theta = scan.pose
    count = int(scan.ranges.size)
    return LaserScan(
        timestamp=_now(), frame_id=frame_id, pose=_pose(x, y, 0.0, theta), start_angle=scan.angle_min,
        end_angle=scan.angle_min + scan.angle_increment * max(count - 1, 0), ranges=scan.ranges.tolist(),
    )


def cloud_message(scan: Any, frame_id: str = DEFAULT_FRAME_ID) -> PointCloud:
    """A fuzzyocc PointCloud's points in the map frame (a 2-D cloud at z = 0), thinned to MAX_CLOUD_POINTS."""
    points = np.asarray(scan.points, dtype=np.float32)
    points = points[:: max(1, math.ceil(len(points) / MAX_CLOUD_POINTS))]
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points), dtype=np.float32)])
    return PointCloud(timestamp=_now(), frame_id=frame_id, pose=_pose(), point_stride=12, fields=CLOUD_FIELDS,
                      data=np.ascontiguousarray(points, dtype="<f4").tobytes())


def plan_message(result: PlanResult, frame_id: str = DEFAULT_FRAME_ID) -> SceneUpdate:
    """The path as one line strip (entity ``plan``: each plan replaces the last); no path, no line."""
    three_d = result.state_space == "R3"
    points = [Point3(x=p[0], y=p[1], z=p[2] if three_d else 0.0) for p in result.path]
    lines = [LinePrimitive(pose=_pose(), thickness=0.05, points=points,
                           color=PLAN_COLOURS.get(result.status, PLAN_COLOURS["approximate"]))] if points else []
    return SceneUpdate(entities=[SceneEntity(timestamp=_now(), frame_id=frame_id, id="plan", lines=lines)])


# ---------------------------------------------------------------- wiring into the service


def client_backlog(max_cells: int) -> int:
    """Messages a client's queue holds: ``CLIENT_BACKLOG_BYTES`` over the largest message, within the bounds."""
    largest = max(max_cells * GRID_CELL.itemsize, MAX_CLOUD_POINTS * 12)  # a grid at the cap, a cloud (xyz float32)
    return max(MIN_CLIENT_BACKLOG, min(MAX_CLIENT_BACKLOG, CLIENT_BACKLOG_BYTES // largest))


def attach(service: Any, *, host: str, port: int, interval_s: float, max_cells: int,
           loop: asyncio.AbstractEventLoop) -> LiveView:
    """Start the live view on ``service`` (a ``MapService``, started) and make it the service's observer."""

    def read_grid(name: str) -> Any:
        # from the publisher thread: the read runs on the event loop (the map's apply lock is an asyncio lock)
        future = asyncio.run_coroutine_threadsafe(service.reads.read_grid(name), loop)
        try:
            return future.result(READ_TIMEOUT_S)
        except TimeoutError:
            future.cancel()  # a read given up on must not hold its place in a map's line or the big reads' lane
            raise

    view = LiveView(host=host, port=port, interval_s=interval_s, read_grid=read_grid, max_cells=max_cells)
    view.start({entry.name: entry.frame_id for entry in service.maps.held_maps})
    service.observer = view
    return view
