"""The bridge's core: ROS LaserScans (+ their TF) in, JSON scan batches out to a fuzzyrisk service.

Pure Python, standard library only, no rclpy: the ROS node (``fuzzyrisk_bridge.node``) only
subscribes and hands each message to :meth:`Bridge.on_scan`; everything below that is here and
tested with messages built by the ``rosbags`` typestore. Messages are duck-typed: any object
with a ``sensor_msgs/msg/LaserScan``'s fields (rclpy's, rosbags', a test's) will do, and a
transform is a ``geometry_msgs/msg/TransformStamped`` ``T_map_laser`` at the scan's stamp.

Threads and failure, the whole contract:

* :meth:`Bridge.on_scan` (the subscription callback) converts the message, puts the scan in a
  bounded queue and returns; it never blocks on the network and **never raises**: a bad message,
  a laser tilted beyond the service's level tolerance (:func:`level_heading`), a failed TF lookup
  or a bug is counted in :class:`BridgeStats` and logged (throttled).
* The queue holds at most ``queue_size`` scans. When it is full the **oldest** scan is dropped,
  counted (``dropped``) and logged: when the service falls behind, the fresh scans describe the
  world as it is now, which is what a robot reading the map needs.
* One worker thread takes up to ``batch_size`` scans (waiting at most ``max_delay_s`` for a batch
  to fill) and POSTs them as one JSON batch. A 503 or 429 is retried after the service's
  ``Retry-After`` (or the backoff when it sends none), a timeout, a refused connection or a
  502/504 after the backoff: ``backoff_s`` doubling per attempt up to ``max_backoff_s``, which
  also caps a ``Retry-After``. After ``max_attempts`` the batch is dropped (``batches_failed``).
  Any other answer (422 invalid scan, 404 no such map, 401 key) is not retried: the batch is
  dropped, counted and logged with the ``code`` and ``message`` of the service's error body.
* Delivery is at least once: a batch whose answer timed out may have been fused, and its retry
  fuses it again (a scan counted twice; the service has no idempotency key).
"""

from __future__ import annotations

import email.utils
import json
import logging
import math
import socket
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

LOG = logging.getLogger("fuzzyrisk_bridge")

#: Answers worth another try: the service is busy (503 with Retry-After), rate-limits (429), or a
#: proxy in between failed (502, 504); 408: the service gave up waiting for the body.
RETRYABLE_STATUS = frozenset({408, 429, 502, 503, 504})

#: ``lookup(frame_id, stamp) -> TransformStamped``: ``T_map_frame`` at ``stamp`` (the node's tf2 buffer).
TransformLookup = Callable[[str, Any], Any]


@dataclass(frozen=True)
class BridgeConfig:
    """Where to post and how patiently. Units in the names: seconds (``_s``)."""

    url: str  # the service, e.g. http://127.0.0.1:8000
    map_name: str
    api_key: str | None = None
    batch_size: int = 10  # scans per POST (the service's FUZZYRISK_MAX_SCANS_PER_BATCH is 256)
    max_delay_s: float = 0.5  # longest a scan waits for its batch to fill
    queue_size: int = 200  # scans held while the service is slow or away (oldest dropped beyond)
    timeout_s: float = 5.0  # per request: connect, and each read of the answer
    backoff_s: float = 0.5  # first wait after a failure without Retry-After; doubles per attempt
    max_backoff_s: float = 10.0  # cap of the backoff and of a Retry-After
    max_attempts: int = 10  # tries of one batch before it is dropped
    log_every_s: float = 10.0  # a repeated warning is logged at most this often (with a count)

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.queue_size < 1 or self.max_attempts < 1:
            raise ValueError("batch_size, queue_size and max_attempts must be at least 1")
        if min(self.max_delay_s, self.timeout_s, self.backoff_s, self.max_backoff_s) < 0:
            raise ValueError("delays and timeouts must not be negative")

    @property
    def scans_url(self) -> str:
        return f"{self.url.rstrip('/')}/maps/{urllib.parse.quote(self.map_name, safe='')}/scans"


@dataclass
class BridgeStats:
    """What happened to the scans handed to the bridge (counters only grow)."""

    received: int = 0  # on_scan / submit calls
    queued: int = 0  # scans converted and queued
    dropped: int = 0  # queued scans pushed out by newer ones (queue full) or left at close
    skipped: int = 0  # messages not usable: no transform, malformed, wrong frame, tilted
    tilted: int = 0  # of the skipped: the laser tilted beyond LEVEL_TOLERANCE_RAD (the service would refuse it)
    errors: int = 0  # unexpected failures inside a callback (a bug), caught
    scans_posted: int = 0  # scans in batches the service acknowledged
    batches_posted: int = 0
    batches_failed: int = 0  # batches given up (not retryable, or out of attempts)
    retries: int = 0  # attempts after the first
    throttled: int = 0  # 503 and 429 answers: the service asked the bridge to slow down
    timeouts: int = 0  # requests that ran into timeout_s
    version: int | None = None  # the map version of the last acknowledged batch

    def as_dict(self) -> dict[str, int | None]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class _Throttle:
    """Log a recurring warning at most once per ``every_s`` per key, saying how many were not logged."""

    def __init__(self, every_s: float) -> None:
        self._every_s = every_s
        self._last: dict[str, float] = {}
        self._silenced: dict[str, int] = {}
        self._lock = threading.Lock()

    def warning(self, key: str, message: str, *args: object) -> None:
        now = time.monotonic()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < self._every_s:
                self._silenced[key] = self._silenced.get(key, 0) + 1
                return
            self._last[key] = now
            silenced = self._silenced.pop(key, 0)
        suffix = f" ({silenced} more since the last such message)" if silenced else ""
        LOG.warning(message + suffix, *args)


# ---------------------------------------------------------------- messages -> JSON scans


def _range(value: float) -> float | str | None:
    """A range as the service's JSON takes it: REP 117 infinities as strings, NaN as null (skipped)."""
    value = float(value)
    if math.isnan(value):
        return None
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return value  # repr of the float64 of a float32 reading: exact, the same bits as a binary upload


#: How far a laser's z axis may lean from the map's vertical (up, or down when mounted upside down)
#: for its scan to go on a 2-D map: ``fuzzyocc.tf.LEVEL_TOLERANCE_RAD``, the service's own limit for a
#: LaserScan posted as CDR (copied, not imported: the bridge uses the standard library only).
LEVEL_TOLERANCE_RAD = math.radians(3.0)


class NotLevel(ValueError):
    """The laser is tilted beyond ``LEVEL_TOLERANCE_RAD``: its scan is not a scan of the map's plane."""


def level_heading(qx: float, qy: float, qz: float, qw: float) -> tuple[float, float]:
    """(theta, turn) of a level laser with orientation ``q`` in the map: its heading, and +1 (z up) or -1 (z down).

    Mirrors ``fuzzyocc.tf.level_heading`` (the rule a LaserScan body posted as CDR meets on a 2-D
    map), so that a scan comes to the same pose whichever way it reaches the service: the quaternion
    normalised first, refused when the z axis leans more than ``LEVEL_TOLERANCE_RAD`` from the
    vertical (``NotLevel``), and upright when the z axis points up (``up > 0``, as the service
    compares). ``tests/app/test_bridge.py`` compares the two over a grid of orientations.
    Raises ``ValueError`` for a quaternion that is not finite or is zero.
    """
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not (math.isfinite(norm) and norm > 0.0):
        raise ValueError(f"the rotation is not a quaternion: {[qx, qy, qz, qw]}")
    qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
    up = 1.0 - 2.0 * (qx * qx + qy * qy)  # z of the laser's z axis in the map frame
    if abs(up) < math.cos(LEVEL_TOLERANCE_RAD):
        tilt = math.degrees(math.acos(min(abs(up), 1.0)))
        raise NotLevel(f"the laser is tilted {tilt:.1f} degrees from level (its z axis against the map's "
                       f"vertical); a 2-D map takes a scan only from a laser level within "
                       f"{math.degrees(LEVEL_TOLERANCE_RAD):g} degrees (z up, or down when mounted upside down)")
    theta = math.atan2(2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qy * qy + qz * qz))
    return theta, (1.0 if up > 0.0 else -1.0)


def scan_to_json(scan: Any, transform: Any) -> dict[str, Any]:
    """One ``sensor_msgs/LaserScan`` with ``T_map_laser`` (a ``TransformStamped``) as a JSON scan.

    The pose is the laser's in the map's plane (:func:`level_heading`: the service's rule): yaw
    from the quaternion; a laser mounted upside down (its z axis pointing down, roll pi) sweeps
    clockwise seen from above, so its angles are negated. The scan's ``header.stamp`` goes with it: the
    service keeps it, and gives it back with the pose in the map's trajectory. Raises ``NotLevel`` for a
    tilted laser, ValueError for a message that cannot be a 2-D scan (non-finite pose or angles, a stamp
    that is not ROS time).
    """
    t = transform.transform
    p, q = t.translation, t.rotation
    values = [float(p.x), float(p.y), float(q.x), float(q.y), float(q.z), float(q.w), float(scan.angle_min),
              float(scan.angle_increment), float(scan.range_min), float(scan.range_max)]
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"non-finite pose or scan parameters: {values}")
    sec, nanosec = int(scan.header.stamp.sec), int(scan.header.stamp.nanosec)
    if sec < 0 or not 0 <= nanosec < 1_000_000_000:
        raise ValueError(f"header.stamp is not ROS time: sec {sec}, nanosec {nanosec}")
    yaw, turn = level_heading(*values[2:6])
    return {
        "header": {"stamp": {"sec": sec, "nanosec": nanosec}},
        "pose": {"x": values[0], "y": values[1], "theta": yaw},
        "angle_min": turn * values[6],
        "angle_increment": turn * values[7],
        "range_min": values[8],
        "range_max": values[9],
        "ranges": [_range(r) for r in scan.ranges],
    }


# ---------------------------------------------------------------- the bridge


class _GiveUp(Exception):
    """A batch that will not be retried: the reason is the message."""


class Bridge:
    """A bounded queue of scans and one worker thread that posts them in batches (see the module doc).

    ``start()`` starts the worker (scans submitted before are kept, up to ``queue_size``);
    ``close()`` sends what is queued within its timeout, then ends the worker. Usable as a context
    manager (started on entry, closed on exit).
    """

    def __init__(self, config: BridgeConfig) -> None:
        self.config = config
        self.stats = BridgeStats()
        self._queue: deque[dict[str, Any]] = deque()
        self._cond = threading.Condition()  # guards the queue, stats and the two flags below
        self._closing = False  # no more scans accepted; the worker sends what is left, without waiting
        self._abort = threading.Event()  # the worker stops now (close's deadline passed)
        self._thread: threading.Thread | None = None
        self._throttle = _Throttle(config.log_every_s)
        self._headers = {"Content-Type": "application/json"}
        if config.api_key:
            self._headers["Authorization"] = f"Bearer {config.api_key}"

    # ------------------------------------------------------------ callbacks: never raise

    def on_scan(self, scan: Any, lookup: TransformLookup) -> None:
        """The subscription callback: look up ``T_map_laser`` at the scan's stamp, then :meth:`submit`.

        ``lookup(frame_id, stamp)`` is the node's tf2 lookup into the map frame; whatever it raises
        (no transform yet, extrapolation) skips this scan. Never raises.
        """
        try:
            header = scan.header
            transform = lookup(header.frame_id, header.stamp)
        except Exception as exc:  # noqa: BLE001 - tf2 raises several types; none may escape a callback
            with self._cond:
                self.stats.received += 1
                self.stats.skipped += 1
            self._throttle.warning("tf", "scan skipped: no transform into the map frame (%s: %s)",
                                   type(exc).__name__, exc)
            return
        self.submit(scan, transform)

    def submit(self, scan: Any, transform: Any) -> None:
        """Queue one scan with its ``T_map_laser``; the oldest queued scan goes when the queue is full.

        Never raises: an unusable message is counted (``skipped``), anything else (``errors``).
        """
        try:
            with self._cond:
                self.stats.received += 1
            try:
                item = scan_to_json(scan, transform)
            except NotLevel as exc:
                with self._cond:
                    self.stats.skipped += 1
                    self.stats.tilted += 1
                self._throttle.warning("tilted", "scan skipped: %s", exc)
                return
            except (AttributeError, TypeError, ValueError) as exc:
                with self._cond:
                    self.stats.skipped += 1
                self._throttle.warning("malformed", "scan skipped: not a usable LaserScan with a transform (%s: %s)",
                                       type(exc).__name__, exc)
                return
            with self._cond:
                if self._closing:
                    self.stats.dropped += 1
                    return
                dropped = len(self._queue) >= self.config.queue_size
                if dropped:
                    self._queue.popleft()
                    self.stats.dropped += 1
                self._queue.append(item)
                self.stats.queued += 1
                self._cond.notify_all()
            if dropped:
                self._throttle.warning("full", "queue full (%d scans): the oldest scan was dropped; the service at %s "
                                       "is slower than the scans or unreachable", self.config.queue_size,
                                       self.config.url)
        except Exception:  # noqa: BLE001 - a bug must not stop rclpy.spin
            try:
                with self._cond:
                    self.stats.errors += 1
                LOG.exception("unexpected error in the scan callback (the scan is lost, the bridge goes on)")
            except Exception:  # noqa: BLE001, S110 - logging itself failed: nothing left to do safely
                pass

    # ------------------------------------------------------------ lifecycle

    def start(self) -> Bridge:
        """Start the worker thread (once)."""
        with self._cond:
            if self._thread is None:
                self._thread = threading.Thread(target=self._work, name="fuzzyrisk-bridge", daemon=True)
                self._thread.start()
        return self

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop accepting scans, send what is queued within ``timeout_s``, then end the worker.

        Scans still queued at the deadline count as ``dropped``; a batch still being retried then, as
        ``batches_failed``.
        """
        with self._cond:
            self._closing = True
            self._cond.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
        self._abort.set()  # a retry wait or a request in flight ends at its next check
        if thread is not None:
            thread.join(self.config.timeout_s + 1.0)
        with self._cond:
            self.stats.dropped += len(self._queue)
            self._queue.clear()

    def __enter__(self) -> Bridge:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def pending(self) -> int:
        """Scans queued and not yet taken into a batch."""
        with self._cond:
            return len(self._queue)

    # ------------------------------------------------------------ the worker

    def _work(self) -> None:
        while not self._abort.is_set():
            batch = self._take_batch()
            if batch is None:
                return
            try:
                self._send(batch)
            except Exception:
                with self._cond:
                    self.stats.errors += 1
                    self.stats.batches_failed += 1
                LOG.exception("unexpected error while posting a batch of %d scans (dropped)", len(batch))

    def _take_batch(self) -> list[dict[str, Any]] | None:
        """Up to ``batch_size`` scans: waits for a first one, then at most ``max_delay_s`` for the rest.

        None once closing with an empty queue (or aborted).
        """
        size = self.config.batch_size
        with self._cond:
            while not self._queue:
                if self._closing or self._abort.is_set():
                    return None
                self._cond.wait()
            deadline = time.monotonic() + self.config.max_delay_s
            while len(self._queue) < size and not self._closing and not self._abort.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            return [self._queue.popleft() for _ in range(min(size, len(self._queue)))]

    def _send(self, batch: list[dict[str, Any]]) -> None:
        """POST one batch, retrying what is worth retrying (module doc); counts the outcome."""
        body = json.dumps({"scans": batch}, allow_nan=False).encode()
        config = self.config
        for attempt in range(1, config.max_attempts + 1):
            if attempt > 1:
                with self._cond:
                    self.stats.retries += 1
            try:
                wait_s = self._post(body, attempt)
            except _GiveUp as exc:
                with self._cond:
                    self.stats.batches_failed += 1
                self._throttle.warning("refused", "batch of %d scans dropped: %s", len(batch), exc)
                return
            if wait_s is None:  # acknowledged
                with self._cond:
                    self.stats.batches_posted += 1
                    self.stats.scans_posted += len(batch)
                return
            if attempt < config.max_attempts and self._abort.wait(wait_s):
                break  # closing: no more waiting
        with self._cond:
            self.stats.batches_failed += 1
        self._throttle.warning("gave-up", "batch of %d scans dropped after %d attempts (service %s)",
                               len(batch), config.max_attempts, config.url)

    def _post(self, body: bytes, attempt: int) -> float | None:
        """One attempt: None when acknowledged, else seconds to wait before the next; ``_GiveUp`` when final."""
        config = self.config
        backoff = min(config.max_backoff_s, config.backoff_s * 2 ** (attempt - 1))
        request = urllib.request.Request(config.scans_url, data=body, headers=self._headers, method="POST")
        try:
            with urllib.request.urlopen(request, timeout=config.timeout_s) as answer:
                reply = json.loads(answer.read() or b"{}")
            with self._cond:
                self.stats.version = reply.get("version", self.stats.version)
            return None
        except urllib.error.HTTPError as exc:
            status, detail = exc.code, _detail(exc)
            if status not in RETRYABLE_STATUS:
                raise _GiveUp(f"{status} from {config.scans_url}: {detail}") from None
            if status in (429, 503):
                with self._cond:
                    self.stats.throttled += 1
            wait_s = _retry_after_s(exc.headers.get("Retry-After"))
            wait_s = backoff if wait_s is None else min(wait_s, config.max_backoff_s)
            self._throttle.warning(f"status-{status}", "%d from the service (%s): retrying in %.2f s",
                                   status, detail, wait_s)
            return wait_s
        except (TimeoutError, socket.timeout) as exc:  # noqa: UP041 - socket.timeout is TimeoutError from 3.10; both named for clarity
            with self._cond:
                self.stats.timeouts += 1
            self._throttle.warning("timeout", "no answer within %.1f s (%s): retrying in %.2f s",
                                   config.timeout_s, exc, backoff)
            return backoff
        except (urllib.error.URLError, ConnectionError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            if isinstance(reason, TimeoutError):
                with self._cond:
                    self.stats.timeouts += 1
            self._throttle.warning("unreachable", "service %s unreachable (%s): retrying in %.2f s",
                                   config.url, reason, backoff)
            return backoff


def _detail(error: urllib.error.HTTPError) -> str:
    """What the service said, for the log: ``CODE: message`` from its error body ``{code, message, details}``.

    Every error answer of the service has that shape (``app.errors.ErrorBody``). Anything else (a
    proxy's page, a server that is not fuzzyrisk, or a fuzzyrisk older than that shape, which
    answered FastAPI's ``{"detail": ...}``) is shown as the first 200 characters of its body, or the
    reason phrase when it has none.
    """
    try:
        raw = error.read(4096)
    except Exception:  # noqa: BLE001 - the answer broke off: the status line is all there is
        return str(error.reason)
    try:
        body = json.loads(raw)
    except ValueError:
        body = None
    if isinstance(body, dict) and isinstance(body.get("code"), str) and "message" in body:
        return f"{body['code']}: {body['message']}"
    text = raw.decode("utf-8", "replace").strip()
    return text[:200] if text else str(error.reason)


def _retry_after_s(value: str | None) -> float | None:
    """``Retry-After`` in seconds: delta-seconds or an HTTP date (RFC 9110); None when absent or unreadable."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())

