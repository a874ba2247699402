"""Read CARMEN laser logs (the format of the classic 2-D SLAM data sets) into :class:`LaserScan` values.

Two message types carry scans with their pose; every other line (``ODOM``, ``PARAM``, ``NEFF``,
comments) is skipped:

- ``FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta ipc_timestamp host logger_timestamp``:
  ``n`` ranges over 180 degrees, the first at -90 degrees, counter-clockwise; 180 or 360 beams
  step ``pi / n`` and end one step short of +90 degrees, 181 or 361 (an odd count) step
  ``pi / (n - 1)`` and include +90. ``x y theta`` is the laser's pose in the map frame (in the
  "corrected" logs, the output of a SLAM run).
- ``ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r_1 .. r_n
  m e_1 .. e_m laser_x laser_y laser_theta ...``: the newer message, which states its angles
  and maximum range itself.

No-returns. A SICK scanner reports "nothing within range" as its maximum reading, which differs
between logs (81.91 m, about 51.1 m with a few centimetres of jitter, 32.767 m). ``FLASER`` does
not state it, so the reader takes the largest reading of the log as the scanner's maximum and
treats every reading within 1 % of it as a no-return (``+inf``, REP 117: free space up to
``range_max``); ``range_max`` of every scan is that 99 % mark. Pass ``max_range`` to state the
maximum yourself.

Stamps. A scan's stamp is its message's timestamp (the logger's, else the IPC one), to the
nanosecond of its decimal text. Some logs' stamps say nothing of time: all 0 (orebro), one value
(belgioioso), two (csail), negative and backwards (infinite-corridor). When a log's stamps are not
all finite, non-negative and strictly increasing, :func:`log_stamps_ns` numbers its scans at
``NUMBERED_RATE_HZ`` from its first stamp instead (from 0 when that is negative or missing), and
:func:`read_carmen` says so.

:func:`grid_for_scans` gives the grid that holds a log's poses and surfaces (any ``LaserScan``
list, in fact), so a log can be mapped without knowing its extent beforehand.
"""

from __future__ import annotations

import gzip
import math
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path

import numpy as np

from fuzzyocc.config import DEFAULT_MAX_CELLS, GridSpec
from fuzzyocc.scans import LaserScan

__all__ = ["CarmenScan", "LogStamps", "NO_RETURN_FRACTION", "NUMBERED_RATE_HZ", "grid_for_scans", "log_stamps_ns",
           "parse_carmen_lines", "read_carmen"]

#: A reading at or above this fraction of the scanner's maximum is a no-return.
NO_RETURN_FRACTION = 0.99

#: Readings below this are skipped (a SICK reports 0 for a dazzled or blocked beam).
RANGE_MIN_M = 0.01

#: The rate at which the scans of a log whose stamps do not increase are numbered (the logs' SICK
#: scanners were logged at about this rate).
NUMBERED_RATE_HZ = 5
_NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class CarmenScan:
    """One scan of a log before the no-return threshold is known: pose, beam angles and raw ranges.

    Attributes
    ----------
    pose : (x, y, theta)
        Laser pose in the map frame, metres and radians.
    angle_min, angle_increment : float
        Angle of beam 0 in the laser frame and the step between beams, radians.
    ranges : (n,) float64 array
        The readings as logged, metres.
    stamp : float
        The message's timestamp (the logger's, else the IPC one), seconds.
    line : int
        1-based line number in the log (for messages that name a scan).
    max_range : float or None
        The maximum range the message states (``ROBOTLASER1``), else None.
    """

    pose: tuple[float, float, float]
    angle_min: float
    angle_increment: float
    ranges: np.ndarray
    stamp: float
    line: int
    max_range: float | None = None

    def to_laser_scan(self, range_max: float, stamp_ns: int | None = None) -> LaserScan:
        """The scan with readings at or above ``range_max`` as no-returns (``+inf``), taken at ``stamp_ns``."""
        ranges = np.where(self.ranges >= range_max, np.inf, self.ranges)
        return LaserScan(pose=self.pose, angle_min=self.angle_min, angle_increment=self.angle_increment,
                         ranges=ranges, range_min=RANGE_MIN_M, range_max=range_max, stamp_ns=stamp_ns)


@dataclass(frozen=True)
class LogStamps:
    """The stamps of a log's scans, Unix nanoseconds in log order, and whether they were numbered (the log's own
    did not increase)."""

    ns: list[int]
    numbered: bool


def _ns_of_seconds(seconds: float) -> int:
    # through the shortest decimal that reads back to the float: a log's "1018930000.15" is 1018930000150000000 ns
    return int((Decimal(repr(seconds)) * _NS_PER_S).to_integral_value())


def log_stamps_ns(stamps: Sequence[float]) -> LogStamps:
    """The stamps of a log's scans from their timestamps (seconds, in log order): the one rule of every reader of a
    log (the importer, the benchmarks).

    Stamps that are finite, non-negative and strictly increasing are kept, to the nanosecond. Any other log's scans
    are numbered at ``NUMBERED_RATE_HZ`` from its first stamp (0 when that is negative or missing): scan ``k`` at
    ``first + k * 200 ms``.
    """
    increasing = all(math.isfinite(s) and s >= 0.0 for s in stamps) and all(b > a for a, b in zip(stamps, stamps[1:]))
    if increasing:
        return LogStamps([_ns_of_seconds(s) for s in stamps], numbered=False)
    first = _ns_of_seconds(stamps[0]) if stamps and math.isfinite(stamps[0]) and stamps[0] > 0.0 else 0
    period = _NS_PER_S // NUMBERED_RATE_HZ
    return LogStamps([first + k * period for k in range(len(stamps))], numbered=True)


def _numbers(fields: list[str], start: int, count: int, what: str, line: int) -> list[float]:
    if len(fields) < start + count:
        raise ValueError(f"line {line}: {what} needs {count} values from field {start}, the line has {len(fields)}")
    values = []
    for index in range(start, start + count):
        try:
            value = float(fields[index])
        except ValueError:
            raise ValueError(f"line {line}: {what}: field {index} is {fields[index]!r}, not a number") from None
        if not math.isfinite(value):
            raise ValueError(f"line {line}: {what}: field {index} is {fields[index]!r}, not a finite number")
        values.append(value)
    return values


def _stamp(fields: list[str], after: int) -> float:
    # ``ipc_timestamp host logger_timestamp``: prefer the logger's; some logs carry only one.
    for index in (after + 2, after):
        try:
            return float(fields[index])
        except (IndexError, ValueError):
            continue
    return math.nan


def _count(fields: list[str], at: int, what: str, line: int, minimum: int) -> int:
    value = _numbers(fields, at, 1, what, line)[0]
    if value != int(value) or value < minimum:
        raise ValueError(f"line {line}: {what} must be a whole number >= {minimum}, got {fields[at]}")
    return int(value)


def _flaser(fields: list[str], line: int) -> CarmenScan:
    n = _count(fields, 1, "FLASER beam count", line, minimum=2)
    ranges = _numbers(fields, 2, n, "FLASER ranges", line)
    x, y, theta = _numbers(fields, 2 + n, 3, "FLASER pose (x y theta)", line)
    step = math.pi / (n - 1) if n % 2 else math.pi / n
    return CarmenScan(pose=(x, y, theta), angle_min=-math.pi / 2, angle_increment=step,
                      ranges=np.asarray(ranges), stamp=_stamp(fields, 2 + n + 6), line=line)


def _robotlaser(fields: list[str], line: int) -> CarmenScan:
    start, _fov, resolution, max_range = _numbers(fields, 2, 4, "ROBOTLASER1 angles and maximum range", line)
    if max_range <= RANGE_MIN_M:
        raise ValueError(f"line {line}: ROBOTLASER1 states a maximum range of {max_range} m")
    n = _count(fields, 8, "ROBOTLASER1 beam count", line, minimum=1)
    if n > 1 and resolution == 0.0:
        raise ValueError(f"line {line}: ROBOTLASER1 has {n} beams and an angular resolution of 0")
    ranges = _numbers(fields, 9, n, "ROBOTLASER1 ranges", line)
    m = _count(fields, 9 + n, "ROBOTLASER1 remission count", line, minimum=0)
    pose_at = 10 + n + m
    x, y, theta = _numbers(fields, pose_at, 3, "ROBOTLASER1 laser pose (x y theta)", line)
    # after the laser pose: robot pose (3), then tv rv forward_safety side_safety turn_axis (5)
    return CarmenScan(pose=(x, y, theta), angle_min=start, angle_increment=resolution,
                      ranges=np.asarray(ranges), stamp=_stamp(fields, pose_at + 3 + 3 + 5), line=line,
                      max_range=max_range)


def parse_carmen_lines(lines: Iterable[str]) -> Iterator[CarmenScan]:
    """The scans of a log's lines, in order; ``ValueError`` naming the line of a malformed scan message."""
    for number, text in enumerate(lines, start=1):
        fields = text.split()
        if not fields:
            continue
        if fields[0] == "FLASER":
            yield _flaser(fields, number)
        elif fields[0] == "ROBOTLASER1":
            yield _robotlaser(fields, number)


def _open(path: Path) -> Iterable[str]:
    if path.suffix == ".gz":
        return gzip.open(path, "rt", encoding="ascii", errors="replace")
    return path.open("r", encoding="ascii", errors="replace")


def read_carmen(path: str | Path, max_range: float | None = None,
                say: Callable[[str], None] | None = None) -> list[LaserScan]:
    """Every scan of a CARMEN log (``.log`` or ``.log.gz``) as a :class:`LaserScan`, in log order, with its stamp
    (:func:`log_stamps_ns`).

    Parameters
    ----------
    path : str or Path
        The log file.
    max_range : float, optional
        The scanner's maximum reading in metres. Default: what a ``ROBOTLASER1`` message
        states, else the largest reading of the log. Readings at or above
        ``NO_RETURN_FRACTION * max_range`` are no-returns.
    say : callable, optional
        Told, in one line, when the log's stamps do not increase and its scans are numbered instead.

    Raises
    ------
    OSError
        The file cannot be read (``FileNotFoundError`` when missing).
    ValueError
        The log holds no scan, or a malformed one (``"<path>: line N: ..."``), or its gzip
        stream is truncated or corrupt.
    """
    path = Path(path)
    if max_range is not None and not (math.isfinite(max_range) and max_range > RANGE_MIN_M / NO_RETURN_FRACTION):
        raise ValueError(f"max_range must be a finite number of metres above {RANGE_MIN_M / NO_RETURN_FRACTION:.4g}, "
                         f"got {max_range}")
    try:
        with _open(path) as lines:  # type: ignore[attr-defined]
            raw = list(parse_carmen_lines(lines))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    except (EOFError, zlib.error) as exc:  # a .gz cut short (a copy that did not finish) or damaged
        raise ValueError(f"{path}: the compressed stream is truncated or corrupt ({exc})") from None
    if not raw:
        raise ValueError(f"{path} holds no FLASER or ROBOTLASER1 line")
    log_max = max(float(s.ranges.max()) for s in raw)
    if max_range is None and log_max * NO_RETURN_FRACTION <= RANGE_MIN_M and any(s.max_range is None for s in raw):
        raise ValueError(f"{path}: every reading is {log_max} m or less, so the scanner's maximum cannot be "
                         "told from the log; pass max_range")
    stamps = log_stamps_ns([s.stamp for s in raw])
    if stamps.numbered and say is not None:
        distinct = len({s.stamp for s in raw})
        say(f"{path.name}: the log's stamps do not increase (the first {raw[0].stamp!r} s, {distinct} distinct "
            f"value{'s' * (distinct != 1)} in {len(raw)}): its scans are numbered at {NUMBERED_RATE_HZ} Hz from "
            f"{Decimal(stamps.ns[0]) / _NS_PER_S} s")
    scans = []
    for s, stamp_ns in zip(raw, stamps.ns, strict=True):
        top = max_range if max_range is not None else (s.max_range if s.max_range is not None else log_max)
        scans.append(s.to_laser_scan(NO_RETURN_FRACTION * top, stamp_ns))
    return scans


def grid_for_scans(scans: Sequence[LaserScan], resolution: float, margin: float = 1.0,
                   max_cells: int = DEFAULT_MAX_CELLS) -> GridSpec:
    """The 2-D grid that holds every scan's pose and hit, padded by ``margin``, snapped to whole cells.

    Only hits count: a no-return clears free space up to ``range_max`` (81 m for a SICK) and
    would stretch the map over empty space; its cells beyond the grid are not mapped. The
    origin is a multiple of ``resolution`` (metres), so maps of one building at one resolution
    share their cell boundaries.

    Raises ``ValueError`` for no scans, a resolution or margin out of range, or a grid of more
    than ``max_cells`` cells (naming the size, so a coarser resolution can be chosen).
    """
    if not scans:
        raise ValueError("no scans: a map needs at least one")
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise ValueError(f"resolution must be a positive number of metres, got {resolution}")
    if not (math.isfinite(margin) and margin >= 0.0):
        raise ValueError(f"margin must be a finite number of metres >= 0, got {margin}")
    points = [np.array([s.pose[:2] for s in scans])]
    for scan in scans:
        rays = scan.to_rays()
        points.append(rays.endpoints[rays.hit])
    xy = np.concatenate(points)
    lower, upper = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    # rounded so a YAML shows -12.35, not -12.350000000000001; 1e-10 m is far below a cell
    origin = tuple(round(math.floor(v / resolution) * resolution, 10) for v in lower)
    cells = [max(1, math.ceil((u - o) / resolution - 1e-9)) for u, o in zip(upper, origin)]
    return GridSpec(origin=origin, size=tuple(n * resolution for n in cells), resolution=resolution,
                    max_cells=max_cells)
