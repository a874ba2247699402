"""A scan batch's body to validated scans, its cast work checked: the same in a parsing thread or a parse process.

Pure functions of the body and the map's grid (no service state), so that ``app.maps.ingest_process`` can run
them in a process of its own.
"""

from __future__ import annotations

from collections.abc import Mapping

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from app.maps import logcodec
from app.scans import BINARY_TYPES, Limits, Scan, from_binary, from_json
from app.ros import messages_in
from app.errors import TooLarge, UnsupportedMediaType
from app.schemas import ScanBatch, ScanQuery
from fuzzyocc import GridSpec, cast_work


def parse(body: bytes, content_type: str, query: Mapping[str, str], dims: int,
          limits: Limits) -> list[Scan]:
    """The scans of a JSON ``ScanBatch``, a binary scan or a ROS 2 message, validated for a map of ``dims``."""
    # the query first, as FastAPI checks query parameters before the route reads a body
    try:
        params = ScanQuery.model_validate(dict(query)).model_dump()
    except ValidationError as exc:
        raise RequestValidationError(_errors(exc, "query")) from None
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
        raise RequestValidationError(_errors(exc, "body")) from None
    return from_json(batch, dims, limits)


def _errors(exc: ValidationError, where: str) -> list[dict[str, object]]:
    """pydantic's errors under ``where``, without inputs that are not scalars: a bad scan's input is all of its
    ranges, which the answer never echoes, and which a parse process would pickle back for nothing."""
    return [{k: v for k, v in {**e, "loc": (where, *e["loc"])}.items()
             if k != "input" or not isinstance(v, dict | list | bytes)} for e in exc.errors(include_url=False)]


def media_of(content_type: str) -> str:
    return content_type.split(";")[0].strip().lower()


def check_work(spec: GridSpec, scans: list[Scan], max_batch_cells: int) -> int:
    """The batch's cast work; 413 when its rays would walk more than ``FUZZYRISK_MAX_BATCH_CELLS`` cells of the map.

    Before it is stored: one small request (12 scans of 16,384 beams reaching past a 16 M-cell
    map's edges) would otherwise hold a fusion thread for a minute, and every restart replays it.
    """
    work = cast_work(spec, scans)
    if work > max_batch_cells:
        raise TooLarge(
            f"the batch's rays walk about {work:,} cells of this map, more than FUZZYRISK_MAX_BATCH_CELLS "
            f"({max_batch_cells:,}): send fewer scans per batch, or shorter range_max"
        )
    return work


def checked_payload(spec: GridSpec, scans: list[Scan], max_batch_cells: int) -> tuple[bytes, int]:
    """``check_work``, then the scans encoded for the log (a refused batch is not encoded): (payload, work)."""
    work = check_work(spec, scans, max_batch_cells)
    return logcodec.encode(scans), work


def prepare(body: bytes, content_type: str, query: Mapping[str, str], dims: int, limits: Limits,
            spec: GridSpec, max_batch_cells: int) -> tuple[list[Scan], bytes, int]:
    """``parse`` and ``checked_payload``: the scans, their encoding and their cast work."""
    scans = parse(body, content_type, query, dims, limits)
    return scans, *checked_payload(spec, scans, max_batch_cells)


def prepare_encoded(body: bytes, content_type: str, query: Mapping[str, str], dims: int, limits: Limits,
                    spec: GridSpec, max_batch_cells: int) -> tuple[bytes, int]:
    """``prepare`` without the scans (``logcodec.decode`` gives them back): what a parse process returns (bytes
    cross a pipe at the cost of a copy; scans would be pickled object by object)."""
    _, payload, work = prepare(body, content_type, query, dims, limits, spec, max_batch_cells)
    return payload, work
