"""Big payloads of the SQLite store as files beside the database, written before the commit that names them.

A commit of an 8 MB batch row took 35-134 ms on a VM disk (WAL, ``synchronous=FULL``), and every
other map's commit waited behind it in the one writer. Written here instead, by the
thread that stores the batch and outside the database's lock, the payload costs the other commits
only a share of the disk: it goes down in pieces, each made durable before the next, so a small
commit's fsync never queues behind megabytes. The row that names the file commits after the file is
on disk, so a committed row always has its file.

Files are named by a random token, written once and never changed, and removed only after the rows
naming them are gone. A file no row names (a crash between the write and its commit, or between a
row's deletion and the file's) is removed when the store next opens, if no other store has the
database open (a lock file says so): another's file being written has no row yet.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import re
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import BinaryIO, Protocol

#: The size of the pieces made durable one at a time: a small commit waits at most about one piece.
PIECE_BYTES = 1 << 20
LOG = logging.getLogger("fuzzyrisk.storage")
_NAME = re.compile(r"[0-9a-f]{32}\.bin")


class PayloadUnreadable(Exception):
    """A payload file a row names is missing or cannot be read (the message says which, and why)."""


class PayloadSource(Protocol):
    def read(self, name: str) -> bytes:
        """The payload of the file ``name``; ``PayloadUnreadable`` when it is missing or cannot be read."""


class PayloadFiles:
    """The directory of a store's big payloads (made at the first write: a read-only data directory still starts)."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self._lock: int | None = None

    def attach(self, named: Callable[[], set[str]]) -> None:
        """Mark the directory in use by this store; alone on it, first remove every file not in ``named()``.

        A shared lock on ``<directory>.lock`` for the store's life; the sweep runs only under an exclusive
        one, so never while another store (a second process on the same data directory) is writing.
        """
        try:
            self._lock = os.open(self.directory.with_name(self.directory.name + ".lock"), os.O_RDWR | os.O_CREAT,
                                 0o644)
        except OSError as exc:  # a read-only data directory: nothing can be written, nothing to sweep
            LOG.info("payload lock file not opened (%s); files no row names are not removed", exc)
            return
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fcntl.flock(self._lock, fcntl.LOCK_SH)
            return
        try:
            self.sweep(named())
        finally:
            fcntl.flock(self._lock, fcntl.LOCK_SH)

    def detach(self) -> None:
        """Give up the lock taken by ``attach``."""
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None

    def write(self, payload: bytes) -> str:
        """Store ``payload`` durably in a new file; its name. ``OSError`` (nothing left behind) when it cannot."""
        name = f"{uuid.uuid4().hex}.bin"
        path = self.directory / name
        view = memoryview(payload)
        try:
            self._make_directory()
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
            with contextlib.suppress(OSError):  # the write's own error is the one to report
                path.unlink(missing_ok=True)
            raise
        return name

    def open(self, name: str) -> BinaryIO:
        """The file ``name``, open for reading (still readable once removed); ``PayloadUnreadable`` if it cannot be."""
        if not _NAME.fullmatch(name):  # a damaged row never makes the store read outside its directory
            raise PayloadUnreadable(f"payload file {name!r} is not a name the store gives")
        try:
            return (self.directory / name).open("rb")
        except FileNotFoundError:
            raise PayloadUnreadable(f"payload file {name} is missing from {self.directory}") from None
        except OSError as exc:
            raise PayloadUnreadable(f"payload file {name} cannot be read: {exc}") from exc

    def read(self, name: str) -> bytes:
        """The payload of the file ``name``; ``PayloadUnreadable`` when it is missing or cannot be read."""
        with self.open(name) as file:
            try:
                return file.read()
            except OSError as exc:
                raise PayloadUnreadable(f"payload file {name} cannot be read: {exc}") from exc

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
        try:
            orphans = [path.name for path in self.directory.iterdir() if _NAME.fullmatch(path.name)
                       and path.name not in named]
        except FileNotFoundError:
            return 0
        except OSError as exc:
            LOG.warning("payload directory %s not swept: %s", self.directory, exc)
            return 0
        self.remove(orphans)
        return len(orphans)

    def _make_directory(self) -> None:
        try:
            self.directory.mkdir()
        except FileExistsError:
            return
        _fsync_path(self.directory.parent)  # the directory's own name, as durable as the files in it

    def _sync_directory(self) -> None:
        # the file's name must be as durable as its bytes before a row names it
        _fsync_path(self.directory)


class Prefetched:
    """Payload files read ahead (outside the store's lock: big files never hold its commits); any other is read
    from its file when asked for.

    One at a time, by name: a file is removed only after every row naming it is gone, so one missing
    here belongs to no row any more (or is damage, reported when its row asks for it).
    """

    def __init__(self, files: PayloadFiles, names: Iterable[str]) -> None:
        self._files = files
        self._contents: dict[str, bytes] = {}
        for name in names:
            with contextlib.suppress(PayloadUnreadable):
                self._contents[name] = files.read(name)

    def read(self, name: str) -> bytes:
        content = self._contents.pop(name, None)
        return self._files.read(name) if content is None else content


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
