"""A scan batch's body to validated scans, its cast work checked: the same in a parsing thread or a parse process.

Pure functions of the body and the map's grid (no service state), so that ``app.maps.ingest_process`` can run
them in a process of its own.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from app.maps import logcodec
from app.scans import BINARY_TYPES, Limits, Scan, from_binary, from_json
from app.ros import messages_in
from app.errors import Invalid, TooLarge, UnsupportedMediaType
from app.schemas import ScanBatch, ScanQuery
from app.schemas.common import located_errors
from fuzzyocc import GridSpec, LaserScan, LatticeSpec, PointCloud, allocation_bound, cast_work
from fuzzyocc.maps import scan_parts


def parse(body: bytes, content_type: str, query: Mapping[str, str], dims: int,
          limits: Limits) -> list[Scan]:
    """The scans of a JSON ``ScanBatch``, a binary scan or a ROS 2 message, validated for a map of ``dims``."""
    # the query first, as FastAPI checks query parameters before the route reads a body
    try:
        params = ScanQuery.model_validate(dict(query)).model_dump()
    except ValidationError as exc:
        raise RequestValidationError(located_errors(exc, ("query",), hidden=_HIDDEN)) from None
    media = media_of(content_type)
    if media in BINARY_TYPES:
        return from_binary(body, params, dims, limits)
    if media in messages_in.MEDIA_TYPES:  # a CDR-serialized LaserScan or PointCloud2, the pose in the query
        return messages_in.from_cdr(body, media, params, dims, limits)
    if media != "application/json":
        # none at all is refused too: a web page can send a body without one, and without a
        # CORS preflight (a browser's no-cors fetch could inject scans)
        given = f"Content-Type {media!r} is not accepted" if media else "a scan upload needs a Content-Type"
        raise UnsupportedMediaType(
            f"{given}: send application/json, or a binary scan as {' or '.join(BINARY_TYPES)}, "
            f"or a ROS 2 message as {' or '.join(map(messages_in.media_type, messages_in.MSGTYPES))}"
        )
    try:
        batch = ScanBatch.model_validate_json(body)
    except ValidationError as exc:
        raise RequestValidationError(located_errors(exc, ("body",), hidden=_HIDDEN)) from None
    return from_json(batch, dims, limits)


#: Inputs an error of a scan body does not echo: a bad scan's input is all of its ranges, which the answer never
#: echoes, and which a parse process would pickle back for nothing.
_HIDDEN = (dict, list, bytes)


def media_of(content_type: str) -> str:
    return content_type.split(";")[0].strip().lower()


@dataclass(frozen=True)
class BatchBudget:
    """What one batch may cost its map, checked before it is stored: the cells its rays walk
    (``FUZZYRISK_MAX_BATCH_CELLS``) and, for a map that holds blocks where scans reach (a fuzzy map), the
    cells it may make the map hold anew (``FUZZYRISK_MAX_NEW_CELLS_PER_BATCH``; None: not counted)."""

    walk: int
    new_cells: int | None


#: Farthest a growing map's sensor or beam end may lie from the frame's origin, metres (422 beyond): its cells'
#: block coordinates are 32-bit, and a robot this far from its map frame has lost it.
MAX_GROWING_COORDINATE_M = 1e6


def check_work(spec: GridSpec | LatticeSpec, scans: list[Scan], budget: BatchBudget) -> int:
    """The batch's cast work; 413 when its rays would walk more than ``FUZZYRISK_MAX_BATCH_CELLS`` cells of the map,
    or make it hold more than ``FUZZYRISK_MAX_NEW_CELLS_PER_BATCH`` new cells; 422 for a growing map's sensor or
    hit farther than ``MAX_GROWING_COORDINATE_M`` from the frame's origin.

    Before it is stored: one small request (12 scans of 16,384 beams reaching past a 16 M-cell
    map's edges) would otherwise hold a fusion thread for a minute, and every restart replays it.
    """
    if isinstance(spec, LatticeSpec):
        _check_reach(scans)
    work = cast_work(spec, scans)
    if work > budget.walk:
        raise TooLarge(
            f"the batch's rays walk about {work:,} cells of this map, more than FUZZYRISK_MAX_BATCH_CELLS "
            f"({budget.walk:,}): send fewer scans per batch, or shorter range_max"
        )
    if budget.new_cells is not None:
        new = allocation_bound(spec, scans)
        if new > budget.new_cells:
            raise TooLarge(
                f"the batch's beams reach blocks of about {new:,} cells, more than FUZZYRISK_MAX_NEW_CELLS_PER_BATCH "
                f"({budget.new_cells:,}) the map may take on at once: send fewer scans per batch, or shorter range_max"
            )
    return work


#: A cloud whose points all lie this near the frame's origin has no hit beyond ``MAX_GROWING_COORDINATE_M``: a hit's
#: end is its point to rounding (nanometres out here), so the margin of a metre spares the rays (a lidar cloud's rays
#: cost 9-12 ms, a pass over its points 0.3 ms).
_SURELY_NEAR_M = MAX_GROWING_COORDINATE_M - 1.0


def _check_reach(scans: list[Scan]) -> None:
    for i, scan in enumerate(scans):
        sensor = np.asarray(scan.pose[:2] if isinstance(scan, LaserScan) else scan.origin, dtype=np.float64)
        if np.any(np.abs(sensor) > MAX_GROWING_COORDINATE_M):
            raise Invalid(f"scans[{i}]: the sensor at {sensor.tolist()} is farther than {MAX_GROWING_COORDINATE_M:.0e} "
                          "m from the map frame's origin: use a local map frame")
        if isinstance(scan, PointCloud) and (not scan.points.size
                                             or max(scan.points.max(), -scan.points.min()) <= _SURELY_NEAR_M):
            continue
        for part in scan_parts(scan):
            rays = scan.to_rays(beams=part)
            hits = rays.endpoints[rays.hit]
            far = np.flatnonzero(np.any(np.abs(hits) > MAX_GROWING_COORDINATE_M, axis=1))
            if far.size:
                raise Invalid(f"scans[{i}]: a beam ends at {hits[far[0]].tolist()}, farther than "
                              f"{MAX_GROWING_COORDINATE_M:.0e} m from the map frame's origin: use a local map frame")


def checked_payload(spec: GridSpec | LatticeSpec, scans: list[Scan], budget: BatchBudget) -> tuple[bytes, int]:
    """``check_work``, then the scans encoded for the log (a refused batch is not encoded): (payload, work)."""
    work = check_work(spec, scans, budget)
    return logcodec.encode(scans), work


def stamped(scans: list[Scan], received_ns: int) -> list[Scan]:
    """The scans, each without a stamp of its own stamped ``received_ns``: when the service received its batch."""
    return [scan if scan.stamp_ns is not None else scan.stamped(received_ns) for scan in scans]


def prepare(body: bytes, content_type: str, query: Mapping[str, str], dims: int, limits: Limits,
            spec: GridSpec | LatticeSpec, budget: BatchBudget, received_ns: int) -> tuple[list[Scan], bytes, int]:
    """``parse``, ``stamped`` and ``checked_payload``: the scans, their encoding and their cast work."""
    scans = stamped(parse(body, content_type, query, dims, limits), received_ns)
    return scans, *checked_payload(spec, scans, budget)


def prepare_encoded(body: bytes, content_type: str, query: Mapping[str, str], dims: int, limits: Limits,
                    spec: GridSpec | LatticeSpec, budget: BatchBudget, received_ns: int) -> tuple[bytes, int]:
    """``prepare`` without the scans (``logcodec.decode`` gives them back): what a parse process returns (bytes
    cross a pipe at the cost of a copy; scans would be pickled object by object)."""
    _, payload, work = prepare(body, content_type, query, dims, limits, spec, budget, received_ns)
    return payload, work
