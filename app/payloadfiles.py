"""Big payloads of the SQLite store as files beside the database, written before the commit that names them.

A commit of an 8 MB batch row took 35-134 ms on a VM disk (WAL, ``synchronous=FULL``), and every
other map's commit waited behind it in the one writer (issue 11, row 6). Written here instead, by the
thread that stores the batch and outside the database's lock, the payload costs the other commits
only a share of the disk: it goes down in pieces, each made durable before the next, so a small
commit's fsync never queues behind megabytes. The row that names the file commits after the file is
on disk, so a committed row always has its file.

Files are named by a random token, written once and never changed, and removed only after the rows
naming them are gone. A file no row names (a crash between the write and its commit, or between a
row's deletion and the file's) is removed when the store next opens.
"""

from __future__ import annotations

import logging
import os
import re
import uuid
from collections.abc import Iterable
from pathlib import Path

#: The size of the pieces made durable one at a time: a small commit waits at most about one piece.
PIECE_BYTES = 1 << 20
LOG = logging.getLogger("fuzzyrisk.storage")
_NAME = re.compile(r"[0-9a-f]{32}\.bin")


class PayloadFiles:
    """The directory of a store's big payloads (made at the first write: a read-only data directory still starts)."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory

    def write(self, payload: bytes) -> str:
        """Store ``payload`` durably in a new file; its name. ``OSError`` (nothing left behind) when it cannot."""
        name = f"{uuid.uuid4().hex}.bin"
        path = self.directory / name
        view = memoryview(payload)
        try:
            self.directory.mkdir(exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            try:
                for start in range(0, len(view), PIECE_BYTES):
                    piece = view[start:start + PIECE_BYTES]
                    while piece:
                        piece = piece[os.write(fd, piece):]
                    os.fdatasync(fd)
                os.fsync(fd)
            finally:
                os.close(fd)
            self._sync_directory()
        except BaseException:
            path.unlink(missing_ok=True)
            raise
        return name

    def read(self, name: str) -> bytes | None:
        """The payload of the file ``name``; None when there is no such file (or the name is not one of ours)."""
        if not _NAME.fullmatch(name):  # a damaged row never makes the store read outside its directory
            return None
        try:
            return (self.directory / name).read_bytes()
        except FileNotFoundError:
            return None

    def remove(self, names: Iterable[str]) -> None:
        """Remove the files ``names`` (whose rows are gone); a file already gone is no error.

        Never raises: the rows are gone already, and a file left behind (a read-only or failing disk)
        is only space, removed at the next open.
        """
        for name in names:
            if _NAME.fullmatch(name):
                try:
                    (self.directory / name).unlink(missing_ok=True)
                except OSError as exc:
                    LOG.warning("payload file %s could not be removed (%s); the next start removes it", name, exc)

    def sweep(self, named: set[str]) -> int:
        """Remove every payload file not in ``named`` (no row names it); how many were removed.

        Only while no write is under way: a file being written has no row yet.
        """
        if not self.directory.is_dir():
            return 0
        orphans = [path.name for path in self.directory.iterdir() if _NAME.fullmatch(path.name)
                   and path.name not in named]
        self.remove(orphans)
        return len(orphans)

    def _sync_directory(self) -> None:
        # the file's name must be as durable as its bytes before a row names it
        fd = os.open(self.directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
