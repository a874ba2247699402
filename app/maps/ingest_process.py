"""Large JSON bodies parsed in a process of their own: scan batches, and corrected trajectories.

pydantic holds the GIL while it validates a JSON body: 12 scans of 16,384 ranges took about 15 ms,
then 3 ms to arrays and 5 ms to rays for the work estimate, every other request of every client
waiting. A keyed client sending such batches back to back (bench abuse row 1: refused 413, 30 a
second) tripled another client's median read. A corrected trajectory of 1,747 poses (400 KB) held it
for 26 ms, in chunks of up to 15 ms, at every PUT. Here they are parsed, checked and encoded in one
process forked from the planner workers' forkserver, 5 steps of niceness below the server; the
server only moves their bytes. Binary and CDR bodies, cheap to read, stay in the parsing threads.

The process ends with the server (as the planner workers do) and is replaced at the next batch if
it dies; a body it was parsing is parsed once more by the new one, and gets a 503 if that one dies too. It starts at the first such batch (about 2 s, once): a
service that never gets one never pays its memory.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
from collections.abc import Callable, Mapping
from concurrent.futures.process import BrokenProcessPool
from typing import TypeVar

from app.scans import Limits
from app.ops import process_setup
from app.ops import forkserver
from app.maps import ingest
from app.errors import Unavailable
from fuzzyocc import GridSpec, LatticeSpec

T = TypeVar("T")

LOG = logging.getLogger("fuzzyrisk.maps")

#: JSON bodies above this are parsed in the process; below it, moving the bytes costs about what parsing does.
PROCESS_PARSE_BYTES = 256 * 1024
#: How much nicer than the server the parse process runs: a flood of large JSON batches takes the CPU that others leave.
PARSE_NICE = 5


def _init() -> None:
    process_setup.start_worker_process(PARSE_NICE)


def wants(body: bytes, content_type: str = "application/json") -> bool:
    """Is this body parsed in the process (a JSON body above ``PROCESS_PARSE_BYTES``)?"""
    return len(body) > PROCESS_PARSE_BYTES and ingest.media_of(content_type) == "application/json"


class ParseProcess:
    """One parse process, started at its first batch, replaced when it dies; none after ``shutdown``."""

    def __init__(self) -> None:
        self._context = forkserver.worker_context()
        self._lock = threading.Lock()
        self._executor: concurrent.futures.ProcessPoolExecutor | None = None
        self._closed = False

    def _pool(self) -> concurrent.futures.ProcessPoolExecutor:
        forkserver.ensure_forkserver(self._context)
        with self._lock:
            if self._closed:
                raise Unavailable("the service is stopping", headers={"Retry-After": "1"})
            if self._executor is None:
                self._executor = concurrent.futures.ProcessPoolExecutor(1, mp_context=self._context, initializer=_init)
            return self._executor

    def _forget(self, pool: concurrent.futures.ProcessPoolExecutor) -> None:
        with self._lock:
            if self._executor is pool:
                self._executor = None

    async def prepare(self, body: bytes, content_type: str, query: Mapping[str, str], dims: int,
                      limits: Limits, spec: GridSpec | LatticeSpec, budget: ingest.BatchBudget,
                      received_ns: int) -> tuple[bytes, int]:
        """``ingest.prepare_encoded`` in the process: the batch encoded (``logcodec.decode`` gives the scans)
        and its cast work; its errors as the parsing threads raise them."""
        return await self.run(ingest.prepare_encoded, body, content_type, dict(query), dims, limits, spec, budget,
                              received_ns)

    async def run(self, fn: Callable[..., T], *args: object) -> T:
        """``fn(*args)`` in the process (a module-level function; arguments, result and errors cross by pickle).
        Parsing stores nothing, so a body whose process died is parsed once more by a new one; ``Unavailable`` (503)
        when that one dies too."""
        loop = asyncio.get_running_loop()
        for attempt in (1, 2):
            pool = await loop.run_in_executor(None, self._pool)  # may start the forkserver: not on the loop
            try:
                future = pool.submit(fn, *args)
            except BrokenProcessPool:  # it died while idle: nothing of this body was sent, a new one takes it
                self._forget(pool)
                if attempt == 2:
                    raise Unavailable("the parse process cannot start; nothing was stored: send the request again",
                                      headers={"Retry-After": "1"}) from None
                continue
            try:
                return await asyncio.wrap_future(future)
            except BrokenProcessPool:
                # Either it died parsing this body, or it died idle and the pool had not noticed when the body
                # was handed to it (the pool learns of a death from a thread of its own). A body that kills the new
                # one too gets the 503.
                self._forget(pool)
                if attempt == 1:
                    LOG.warning("the parse process died before this body was parsed; a new one parses it")
                    continue
                LOG.error("the parse process died parsing a body; a new one takes the next")
                raise Unavailable("the process parsing this request died (out of memory?); nothing was stored: "
                                  "send it again", headers={"Retry-After": "1"}) from None
        raise AssertionError("unreachable")  # pragma: no cover

    def shutdown(self) -> None:
        with self._lock:
            executor, self._executor, self._closed = self._executor, None, True
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)
