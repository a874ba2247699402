"""A bag file uploaded into a map (``POST /maps/{name}/bags``): written to a file, bounded, read and fused batch by batch.

The steps, each before the work it guards:

1. admission (the map's line of batches, as a scan upload's: ``WritePath.receiving``, which counts the body
   against the line while it arrives) and the Content-Type, before the body is read;
2. the container, told by its first bytes (``CONTAINERS``), before anything is written;
3. the body written to ``<data dir>/tmp`` (rosbags reads files; the data directory's disk, not a
   tmpfs ``/tmp`` that would hold the body in memory); a disk that cannot take it answers as a
   full store does (``StorageUnavailable``: 503 ``STORAGE_UNAVAILABLE`` with ``Retry-After``);
4. the size its chunks declare decompressed (``app.ros.bagsize``), against ``FUZZYRISK_MAX_BAG_BYTES``;
5. the scans read, placed and converted in a thread (``app.ros.bags.BagStream``), one batch of
   ``FUZZYRISK_MAX_SCANS_PER_BATCH`` at a time, each fused through ``WritePath.add_parsed_scans``
   (ticket, group commit, apply) before the next is read: one batch in memory, never the bag.

All or what was done: the import is admitted once, at its first batch; later batches are not
refused for the line's length. A failure before the first batch is applied answers its own error
(nothing applied); a failure after it (a full disk, the map deleted, a chunk that does not
decompress) answers 200 with ``complete: false``, the error in ``stopped`` and what was applied,
never a retryable 5xx: a client that sent the bag again would fuse its first part twice.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import IO, Any, TypeVar

from anyio import to_thread

from app.ros import bagsize
from app.errors import (
    Invalid,
    ServiceError,
    TooLarge,
    UnsupportedMediaType,
    error_body_of,
)
from app.ros.bags import BagOptions, BagScan, BagStream, BagUnreadable
from app.maps import in_use
from app.formats.mediatypes import MCAP, OCTET_STREAM, ROSBAG, X_MCAP
from app.schemas import BagImportResult, ErrorBody
from app.service.mapservice import MapService
from app.storage import StorageUnavailable

LOG = logging.getLogger("fuzzyrisk.bags")
T = TypeVar("T")

#: Content-Type -> (the file's first bytes, the suffix rosbags reads it by).
CONTAINERS = {
    ROSBAG: (bagsize.ROS1_MAGIC, ".bag"),
    MCAP: (bagsize.MCAP_MAGIC, ".mcap"),
    X_MCAP: (bagsize.MCAP_MAGIC, ".mcap"),
}
#: Every accepted Content-Type: a container's, or application/octet-stream (what generated clients send for a
#: file), told by its first bytes.
MEDIA_TYPES = (*CONTAINERS, OCTET_STREAM)
#: The temporary file of an upload: ``<data dir>/tmp/fuzzyrisk-bag-*`` (what a killed run left goes at start).
TEMP_PREFIX = "fuzzyrisk-bag-"
_MAGIC_BYTES = max(len(magic) for magic, _ in CONTAINERS.values())
#: Body bytes gathered before one write (a thread's trip per write, not per network chunk).
_WRITE_BYTES = 1 << 20


async def import_upload(
    service: MapService, name: str, *, content_type: str, body: AsyncIterator[bytes], map_frame: str | None,
    topics: tuple[str, ...], pose_topic: str | None, pose_frame: str, range_max: float,
) -> BagImportResult:
    """Import the bag ``body`` (of ``content_type``) into map ``name``; ``map_frame`` None: the map's ``frame_id``."""
    # admitted before the body is read (a map with a full line answers at once), and counted against the map's
    # line while it arrives; no longer once it is read: the import's first batch must not wait behind itself
    async with service.writes.receiving(name) as entry:
        frame_id, dims, version, uid = entry.frame_id, entry.spec.ndim, entry.version, entry.uid
        media = content_type.split(";")[0].strip().lower()
        if media not in MEDIA_TYPES:
            raise UnsupportedMediaType(f"Content-Type {media!r} is not a bag: send a ROS 1 .bag as {ROSBAG} or a "
                                       f"rosbag2 .mcap file as {MCAP} (or {X_MCAP}; {OCTET_STREAM}: told by its first "
                                       "bytes)")
        path = await _spool(body, media, service.settings.temp_dir)
    options = BagOptions(map_frame=map_frame or frame_id, topics=topics, pose_topic=pose_topic,
                         pose_frame=pose_frame, cloud_range_max=range_max)
    # in use until the import ends (no await since the body was read): a replica must not drop the map from
    # memory between its batches, or the next batch would find another copy (another uid) of it
    try:
        with in_use(entry):
            declared = await _reading(bagsize.decompressed_bytes, path)
            limit = service.settings.max_bag_bytes
            if declared > limit:
                raise TooLarge(f"body: the bag's chunks decompress to {declared:,} bytes, more than "
                               f"FUZZYRISK_MAX_BAG_BYTES ({limit:,}): split the bag (ros2 bag convert, "
                               "rosbags-convert)")
            stream = BagStream(path, options, dims=dims, limits=service.writes.limits)
            return await _fuse(service, name, uid, stream, version)
    finally:
        await to_thread.run_sync(_remove, path)


def remove_leftovers(temp_dir: Path) -> None:
    """Remove the files of uploads a killed run left in ``temp_dir`` (at start, before any upload)."""
    for path in temp_dir.glob(f"{TEMP_PREFIX}*"):
        _remove(path)


# ---------------------------------------------------------------- the body to a file


def _container(media: str, head: bytes) -> str:
    """The suffix rosbags reads the body by, from its Content-Type and its first bytes."""
    if media == OCTET_STREAM:
        for magic, suffix in CONTAINERS.values():
            if head.startswith(magic):
                return suffix
        raise Invalid("body: neither a ROS 1 .bag nor an .mcap file (it starts as neither)")
    magic, suffix = CONTAINERS[media]
    if not head.startswith(magic):
        raise Invalid(f"body: not a {suffix} file (it does not start as one); check the file and its Content-Type")
    return suffix


async def _spool(body: AsyncIterator[bytes], media: str, directory: Path) -> Path:
    """The body in a new file of ``directory``, named for its container; 422 before a byte is written when its
    first bytes are no bag. ``StorageUnavailable`` when the disk cannot take it (full, read-only)."""
    chunks = aiter(body)
    head = b""
    async for chunk in chunks:
        head += chunk
        if len(head) >= _MAGIC_BYTES:
            break
    suffix = _container(media, head)
    try:
        path, out = await to_thread.run_sync(_create, directory, suffix)
    except OSError as exc:
        raise StorageUnavailable(f"cannot create an upload's file in {directory}: {exc}") from exc
    try:
        pending, size = [head], len(head)
        async for chunk in chunks:
            pending.append(chunk)
            size += len(chunk)
            if size >= _WRITE_BYTES:
                await to_thread.run_sync(out.write, b"".join(pending))
                pending, size = [], 0
        await to_thread.run_sync(out.write, b"".join(pending))
        await to_thread.run_sync(out.close)
    except BaseException as exc:
        await to_thread.run_sync(_close_and_remove, out, path)
        if isinstance(exc, OSError):
            raise StorageUnavailable(f"cannot write an upload's file in {directory}: {exc}") from exc
        raise
    return path


def _create(directory: Path, suffix: str) -> tuple[Path, IO[bytes]]:
    directory.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(suffix=suffix, prefix=TEMP_PREFIX, dir=directory)
    return Path(name), os.fdopen(handle, "wb")


def _close_and_remove(out: IO[bytes], path: Path) -> None:
    try:
        out.close()
    except OSError:
        pass  # a full disk again: the file goes anyway
    _remove(path)


def _remove(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError:
        LOG.warning("an uploaded bag's file could not be removed", extra={"fields": {"path": str(path)}})


# ---------------------------------------------------------------- the bag, batch by batch


async def _reading(fn: Callable[..., T], *args: Any) -> T:
    """``fn(*args)`` on the bag, in a thread; what the file makes it raise is a 422 (``Invalid``).

    The thread is always waited for, a cancelled request too (anyio's default): the bag's reader is
    never closed under a read.
    """
    try:
        return await to_thread.run_sync(fn, *args)
    except ServiceError:
        raise
    except bagsize.BagSizeUnknown as exc:
        raise Invalid(f"body: not a readable bag ({exc})") from None
    except BagUnreadable as exc:
        raise Invalid(f"body: {exc}") from None
    except Exception as exc:
        # rosbags is not hardened against hostile files: a mutated bag raises KeyError, AssertionError,
        # UnicodeDecodeError, MemoryError (a length field read as a size)...: the body's fault, not ours
        LOG.warning("an uploaded bag could not be read", exc_info=True)
        raise Invalid(f"body: not a readable bag ({type(exc).__name__}: {str(exc)[:200]})") from None


async def _fuse(service: MapService, name: str, uid: int, stream: BagStream, version: int) -> BagImportResult:
    """Read, then fuse, one batch at a time; the summary, complete or stopped part-way (``BagImportResult``)."""
    await _reading(stream.__enter__)
    batches = stream.batches(service.writes.limits.max_scans)
    done = {"scans_fused": 0, "rays": 0, "cells_updated": 0, "batches": 0, "version": version}
    stopped: ErrorBody | None = None
    try:
        while True:
            try:
                batch: list[BagScan] | None = await _reading(next, batches, None)
                if batch is None:
                    break
                # admitted once, at the first batch: the import's later batches are never refused for the line
                result = await service.writes.add_parsed_scans(name, [s.scan for s in batch], uid=uid,
                                                        admitted=done["batches"] > 0)
            except Exception as exc:
                if not done["batches"]:
                    raise  # nothing applied: the error's own answer
                stopped = _stopped(name, exc, done)
                break
            done["scans_fused"] += result.scans_fused
            done["rays"] += result.rays
            done["cells_updated"] += result.cells_updated
            done["batches"] += 1
            done["version"] = result.version
    finally:
        await to_thread.run_sync(_close, batches, stream)
    return BagImportResult(complete=stopped is None, stopped=stopped, messages=stream.messages,
                           skipped=dict(stream.skipped), topics=stream.topics, **done)


def _stopped(name: str, exc: Exception, done: dict[str, int]) -> ErrorBody:
    """The error that stopped an import part-way, as its error body, saying what was applied before it."""
    body = error_body_of(exc)
    if isinstance(exc, (ServiceError, StorageUnavailable)):
        LOG.warning("a bag import stopped part-way: %s", exc,
                    extra={"fields": {"map": name, "batches_applied": done["batches"], "code": body["code"]}})
    else:  # a bug: the traceback, which no error handler logs now
        LOG.error("a bag import stopped part-way", exc_info=exc,
                  extra={"fields": {"map": name, "batches_applied": done["batches"]}})
    body["message"] = (f"the import stopped after {done['batches']} batches ({done['scans_fused']} scans, map "
                       f"version {done['version']}), which are applied and durable; then: {body['message']}")
    return ErrorBody(**body)


def _close(batches: Any, stream: BagStream) -> None:
    batches.close()  # the generator first: it reads through the stream's reader
    stream.close()
