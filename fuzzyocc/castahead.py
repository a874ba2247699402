"""Batches fused in order, the next cast chunk cast in a second thread while this one fuses.

A stream fuses one batch at a time and cannot know the next; a replay of a stored history can. A cast reads the
map's blocks and a fusion writes their cells: once a chunk's new blocks are entered, the next chunk (of the same
batch, or of the batch the caller says comes next) can be cast beside its fusion, on the other core, and the map is
the one ``integrate_batch`` of each batch in turn makes, bit for bit. A 2-D chunk (16 M cast entries: a few CARMEN
scans on a large map) is cast on one thread, so without this one core idles while the other casts or fuses.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields
from concurrent.futures import Future, ThreadPoolExecutor
from types import TracebackType

from fuzzyocc import parallel
from fuzzyocc.maps import IntegrationStats, OccupancyMap, PreparedBatch, Scan


class CastAhead:
    """Fuses batches of scans into ``model`` in order (:meth:`integrate`), each cast chunk's successor cast while it
    fuses.

    A context manager: leaving it waits for a cast still running (it reads the map's blocks), so nothing touches the
    map after it. Between two calls the map must not change otherwise (a clear, a prior): the caller names no next
    batch before such a change.
    """

    def __init__(self, model: OccupancyMap) -> None:
        self._model = model
        self._thread: ThreadPoolExecutor | None = None
        self._ahead: Future[PreparedBatch | None] | None = None

    def __enter__(self) -> CastAhead:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def integrate(self, scans: Sequence[Scan], following: Sequence[Scan] | None = None) -> IntegrationStats:
        """``model.integrate_batch(scans)`` (``ValueError`` as it raises it, the map unchanged); ``following``: the
        scans the next call fuses, whose first chunk is cast while this batch's last one fuses."""
        chunks = self._model.chunked(scans)
        upcoming: list[Scan] | None = None
        if following:
            try:
                upcoming = self._model.chunked(following)[0]
            except ValueError:
                pass  # the next call raises it
        done = [self._fuse(chunk, chunks[c + 1] if c + 1 < len(chunks) else upcoming)
                for c, chunk in enumerate(chunks)]
        return IntegrationStats(**{f.name: sum(getattr(s, f.name) for s in done) for f in fields(IntegrationStats)})

    def _fuse(self, chunk: list[Scan], upcoming: list[Scan] | None) -> IntegrationStats:
        """One chunk fused, ``upcoming`` cast beside it where the map allows it (its blocks stay as they are during
        the fusion: no forgetting; a chunk of one scan cast in parts is cast as it fuses)."""
        model = self._model
        prepared = self._take(chunk)
        if upcoming and model.forget_beyond is None:
            if prepared is None:
                prepared = model.prepare_batch(chunk)
            if prepared is not None:
                prepared = model.enter_prepared(prepared)
            if prepared is not None:  # the map's blocks now stay as they are until this fusion ends
                if self._thread is None:
                    self._thread = parallel.beside("cast-ahead")
                self._ahead = self._thread.submit(model.prepare_batch, upcoming)
        return model.integrate_batch(chunk, prepared)

    def _take(self, chunk: list[Scan]) -> PreparedBatch | None:
        """The cast made ahead, if it was of ``chunk`` and succeeded; waits for it."""
        if self._ahead is None:
            return None
        future, self._ahead = self._ahead, None
        try:
            prepared = future.result()
        except Exception:  # noqa: BLE001 - the same cast in the caller's thread raises it where it belongs
            return None
        return prepared if prepared is not None and prepared.of(chunk) else None

    def close(self) -> None:
        """Wait for a cast still running, and end the thread."""
        if self._ahead is not None:
            self._ahead.exception()  # waited for, whatever it raised: its chunk is not fused
            self._ahead = None
        if self._thread is not None:
            self._thread.shutdown(wait=True)
            self._thread = None
