"""``check_path``: whether a given path holds on a field, by the planner's own dense check (Nav2's ``IsPathValid``).

The path's points are joined by straight segments, and every cell each segment crosses is checked
against the field dilated by the robot, as ``plan`` verifies every path it returns
(``PackedGrid.evaluate``): the same footprint and validity rule (``RiskField.valid_mask``), the same
cost (length + risk_weight x the integral of dilated risk) and the same compiled walk
(``_segment_kernels``). A motion model's curves are checked as the dense points a plan returns for
them, each step a straight chord.

Only the part of the field the path reaches is dilated and packed: the box of the cells holding the
path's points, two cells wider (a walk's rounding can carry it a cell past its end), and for the
dilation wider again by the footprint's reach. A cell's dilated value depends on no cell beyond that
reach, so inside the box it is the whole field's. The box is packed with origin 0 and resolution 1,
and each point is walked at its cell coordinates in the whole field, ``(x - origin) * (1 / resolution)``
as the kernel computes them, less the box's integer offset. Subtracting an integer no larger than a
float is exact, so the walk meets the same cells at the same parameters as on the whole field: the
answer is ``PackedGrid(field, ...).evaluate``'s bit for bit (``tests/planning/test_path_check.py``),
for the work of the box rather than of the map.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from planning import _segment_kernels
from planning.checks import check_point, check_rules, space_spec
from planning.field import DEFAULT_MAX_RISK, RiskField, footprint_reach
from planning.parameters import DEFAULT_ALLOW_UNKNOWN, DEFAULT_RISK_WEIGHT, DEFAULT_ROBOT_RADIUS
from planning.result import PathCheck

#: Most cells the segments of one path may cross, counted before the walk starts (about 50 ms of walking): two points
#: across a big map are thousands of cells, and a path may hold thousands of points.
MAX_WALK_CELLS = 10_000_000
#: Cells the box of the path's points is widened by, beyond which no walk between them steps.
_PAD = 2


class PathTooLong(ValueError):
    """The segments of a path cross more cells than a check walks (``MAX_WALK_CELLS``)."""


def check_path(
    field: RiskField,
    path: Sequence[Sequence[float]],
    state_space: str | None = None,
    robot_radius: float = DEFAULT_ROBOT_RADIUS,
    max_risk: float = DEFAULT_MAX_RISK,
    risk_weight: float = DEFAULT_RISK_WEIGHT,
    allow_unknown: bool = DEFAULT_ALLOW_UNKNOWN,
) -> PathCheck:
    """Check ``path`` on ``field`` under the rules a plan with these arguments is held to.

    Parameters
    ----------
    field : RiskField
    path : sequence of points
        At least one, each as a state of ``state_space``: (x, y) in R2, (x, y, theta) in SE2 /
        Dubins / ReedsShepp (theta is not checked: the footprint is a disk), (x, y, z) in R3.
    state_space, robot_radius, max_risk, risk_weight, allow_unknown
        As ``plan`` takes them, with the same defaults and bounds.

    Raises
    ------
    ValueError
        An argument out of range, naming it; a point of the wrong size or not finite, naming it.
    PathTooLong
        The segments cross more than ``MAX_WALK_CELLS`` cells.
    """
    if not isinstance(field, RiskField):
        raise ValueError(f"field: must be a RiskField, got {type(field).__name__}")
    sspec = space_spec(state_space, field)
    rules = check_rules(field, robot_radius, max_risk, risk_weight, allow_unknown)
    positions = _points(path, sspec.state_dim, sspec.name)[:, : field.ndim]
    shape = np.asarray(field.shape)
    # the cell coordinates the kernel computes on the whole field: (x - origin) * (1 / resolution)
    units = (positions - np.asarray(field.origin)) * (1.0 / field.resolution)
    inside = ((units >= 0.0) & (units < shape)).all(axis=1)
    cells = np.floor(np.where(inside[:, None], units, 0.0)).astype(np.int64)
    _check_walk(cells, inside)

    if inside.any():
        lo = np.maximum(cells[inside].min(axis=0) - _PAD, 0)
        hi = np.minimum(cells[inside].max(axis=0) + 1 + _PAD, shape)
    else:  # every segment leaves the map: any one cell will do
        lo, hi = np.zeros_like(shape), np.ones_like(shape)
    reach = footprint_reach(rules.robot_radius, field.resolution)
    dlo, dhi = np.maximum(lo - reach, 0), np.minimum(hi + reach, shape)
    window = tuple(slice(a, b) for a, b in zip(dlo, dhi, strict=True))
    part = RiskField(field.risk[window], field.resolution, field.origin, observed=field.observed[window])
    box = tuple(slice(a - d, b - d) for a, b, d in zip(lo, hi, dlo, strict=True))
    risk = part.dilated_risk(rules.robot_radius)[box]
    valid = part.valid_mask(rules.robot_radius, rules.max_risk, rules.allow_unknown)[box]
    buffer = _segment_kernels.pack(risk, valid, (0.0,) * field.ndim, 1.0, rules.risk_weight)

    walk = units - lo  # exact for every point on the map; a point off it stays off the box
    metres = positions
    if field.ndim == 2:  # as ``PackedGrid`` walks a 2-D grid: one layer, z in its middle
        walk = np.column_stack([walk, np.full(len(walk), 0.5)])
        metres = np.column_stack([metres, np.full(len(metres), 0.5 * field.resolution)])
    length, integral, peak, bad = _segment_kernels.evaluate_walk(
        buffer, np.ascontiguousarray(walk), np.ascontiguousarray(metres))
    on_map = bool(inside.all())
    return PathCheck(
        valid=bad < 0,
        first_invalid_index=None if bad < 0 else int(bad),
        max_risk=float(peak) if on_map else None,
        cost=float(length + rules.risk_weight * integral) if on_map else None,
        length=float(length) if on_map else None,
    )


def _points(path: Any, size: int, space: str) -> np.ndarray:
    """``path`` as a (K, size) float64 array of finite numbers, K >= 1; ValueError naming the first bad point."""
    try:
        items = list(path)
    except TypeError:
        raise ValueError(f"path: must be a sequence of points, got {type(path).__name__}") from None
    if not items:
        raise ValueError("path: needs at least one point")
    try:
        points = np.asarray(items, dtype=np.float64)
    except (TypeError, ValueError):  # ragged, or not numbers: the loop below names the point
        points = None
    if points is not None and points.shape == (len(items), size) and np.isfinite(points).all():
        return points
    for k, point in enumerate(items):
        check_point(f"path[{k}]", point, size, space)
    raise ValueError(f"path: must be a sequence of points of {size} numbers")  # pragma: no cover - named above


def _check_walk(cells: np.ndarray, inside: np.ndarray) -> None:
    """Raise PathTooLong when the segments with both ends on the map cross more than ``MAX_WALK_CELLS`` cells
    (a segment with an end off the map is not walked)."""
    if len(cells) < 2:
        return
    walked = inside[:-1] & inside[1:]
    steps = np.abs(np.diff(cells, axis=0)).sum(axis=1) + 1
    total = int(steps[walked].sum())
    if total > MAX_WALK_CELLS:
        raise PathTooLong(f"path: its segments cross {total:,} cells, more than the {MAX_WALK_CELLS:,} a check "
                          "walks; check it in parts")
