"""Group commit: one writer thread makes scan batches durable, several per transaction when they queue up.

Every fsync of SQLite's WAL costs about as much for one batch as for ten, so the batches
that arrive while a transaction is being written (from any maps) share the next one. A
batch's future resolves only once the transaction holding it is on disk (``synchronous=FULL``
is untouched), so "committed before acknowledged" holds for each of them.

The writer is a thread of its own, not one of the fusion threads: a commit never waits
behind a fusion, and an fsync (waiting on the disk, not the CPU) never holds a fusion thread.

A batch of more than ``INLINE_BYTES`` is committed alone, on a second writer thread: its payload
takes tens of milliseconds to reach the disk, and in the group it held every other map's commit
for as long (an innocent's scan p99 of 42 ms beside two maps of 8 MB scans). The store
writes such a payload before it takes its own lock (``app.storage.payloadfiles``), so the small commits
go on meanwhile. A map's batches still commit in order: its line lets one in at a time.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

from app.ops.metrics import Metrics
from app.storage.base import INLINE_BYTES, BatchRecord, CommitUncertain, Storage


@dataclass
class _Pending:
    record: BatchRecord
    future: Future[int] = field(default_factory=Future)
    queued: float = field(default_factory=time.perf_counter)


class GroupCommitter:
    """Appends batches through ``Storage.append_batches``, grouping those that wait for the writer.

    A group whose transaction fails is retried batch by batch, so one batch's failure (say, the
    one that does not fit on a nearly full disk) is its own; each then fails or succeeds exactly
    as if it had been committed alone. Storage stays all or nothing per transaction, so a failed
    batch is never partly on disk.
    """

    def __init__(self, storage: Storage, metrics: Metrics) -> None:
        self._storage = storage
        self._metrics = metrics
        self._lock = threading.Lock()
        self._pending: list[_Pending] = []
        self._closed = False
        self._writer = ThreadPoolExecutor(1, thread_name_prefix="commit")
        self._big_writer = ThreadPoolExecutor(1, thread_name_prefix="commit-big")

    def append(self, record: BatchRecord) -> Future[int]:
        """Queue a batch; the future resolves to the version the store gave it once it is on disk, or fails
        (``StorageUnavailable``, ``MapGone``: nothing stored)."""
        item = _Pending(record)
        with self._lock:
            if self._closed:
                raise RuntimeError("the committer is shut down")
            if len(record.payload) > INLINE_BYTES:
                self._big_writer.submit(self._commit_big, item)
            else:
                self._pending.append(item)
                # one flush per batch queued: a flush takes everything pending, so later ones may find nothing
                self._writer.submit(self._flush)
        return item.future

    def _commit_big(self, item: _Pending) -> None:
        if not item.future.set_running_or_notify_cancel():
            return
        try:
            self._commit_alone(item)
        finally:
            _answer_the_rest([item])

    def _flush(self) -> None:
        with self._lock:
            group, self._pending = self._pending, []
        # a future cancelled before it was written is dropped (its batch is not written); the rest can no
        # longer be cancelled, so each is resolved exactly once below
        group = [item for item in group if item.future.set_running_or_notify_cancel()]
        try:
            if not group:
                return
            try:
                versions = self._storage.append_batches([item.record for item in group])
            except BaseException as exc:
                if len(group) == 1 or isinstance(exc, CommitUncertain):
                    # a group that may have committed is not retried: its batches would be stored twice
                    for item in group:
                        item.future.set_exception(exc)
                    return
                for item in group:
                    self._commit_alone(item)
                return
            self._resolve(group, versions)
        finally:
            _answer_the_rest(group)

    def _commit_alone(self, item: _Pending) -> None:
        try:
            versions = self._storage.append_batches([item.record])
        except BaseException as exc:
            item.future.set_exception(exc)
        else:
            self._resolve([item], versions)

    def _resolve(self, group: list[_Pending], versions: list[int]) -> None:
        now = time.perf_counter()
        for item, version in zip(group, versions, strict=True):
            item.future.set_result(version)
        self._metrics.commit_groups.observe(len(group))
        for item in group:
            self._metrics.commit_seconds.observe(now - item.queued)

    def shutdown(self) -> None:
        """Write what is queued, then stop the writer."""
        with self._lock:
            self._closed = True
        self._big_writer.shutdown(wait=True)
        self._writer.shutdown(wait=True)


def _answer_the_rest(items: list[_Pending]) -> None:
    """Fail the batches left without an answer: whatever went wrong, no writer may wait forever (it holds its
    map's commit turn)."""
    for item in items:
        if not item.future.done():
            item.future.set_exception(RuntimeError("the batch's commit ended without an answer"))
