"""A file of reserved space in the data directory, given up so that a full disk can still be freed.

On a full disk every SQLite write fails, the deletion of a map included (it appends to the WAL
first): space could not be freed through the API. The service keeps a file of
``FUZZYRISK_DISK_RESERVE_BYTES`` beside its database; when a deletion meets a full disk, the file
goes, the deletion is tried again, and the file comes back once there is room.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

LOG = logging.getLogger("fuzzyrisk.storage")
NAME = "disk-reserve"
_BLOCK = 1 << 20


class DiskReserve:
    """The reserve file: ``hold`` (make it, when there is room), ``release`` (remove it)."""

    def __init__(self, directory: Path, size_bytes: int) -> None:
        self.path = directory / NAME
        self.size_bytes = size_bytes

    @property
    def held(self) -> bool:
        try:
            return self.path.stat().st_size >= self.size_bytes > 0
        except FileNotFoundError:
            return False

    def hold(self) -> bool:
        """Make the file (written, not sparse: a sparse file reserves nothing); False when there is no room."""
        if self.size_bytes <= 0 or self.held:
            return self.held
        partial = self.path.with_suffix(".partial")
        try:
            with partial.open("wb") as out:
                left = self.size_bytes
                while left > 0:
                    left -= out.write(b"\0" * min(_BLOCK, left))
                out.flush()
                os.fsync(out.fileno())
            partial.replace(self.path)
        except OSError as exc:
            partial.unlink(missing_ok=True)
            LOG.warning("no room for the disk reserve (FUZZYRISK_DISK_RESERVE_BYTES); a full disk may then refuse "
                        "map deletions", extra={"fields": {"path": str(self.path), "error": str(exc)}})
            return False
        return True

    def release(self) -> bool:
        """Remove the file; True if there was one to give up."""
        try:
            self.path.unlink()
        except FileNotFoundError:
            return False
        LOG.warning("disk full: the disk reserve is given up so that a deletion can go through",
                    extra={"fields": {"path": str(self.path), "bytes": self.size_bytes}})
        return True
