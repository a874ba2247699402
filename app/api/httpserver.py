"""uvicorn's HTTP/1.1 protocol with a deadline on request headers (slow clients).

uvicorn bounds the size of a request's headers (h11's incomplete-event limit) and the idle time
between requests (keep-alive), but not the time headers take to arrive: a client that trickles
one header byte every few seconds holds its connection open for ever (its bytes even cancel the
keep-alive timer), and a few thousand such clients hold every socket. Here each request's
headers must be complete within ``FUZZYRISK_HEADER_TIMEOUT_S`` of the connection (or of the end
of the previous response on a kept-alive connection); otherwise the connection is closed. The
body has its own deadline (``FUZZYRISK_BODY_READ_TIMEOUT_S``, ``app.api.middleware``).
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from uvicorn.protocols.http.h11_impl import H11Protocol

LOG = logging.getLogger("fuzzyrisk.http")


class HeaderDeadlineProtocol(H11Protocol):
    """``H11Protocol`` that closes a connection whose request headers are not complete in time."""

    header_timeout_s = 10.0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def data_received(self, data: bytes) -> None:
        cycle = self.cycle
        super().data_received(data)
        if self.cycle is not cycle:  # a request's headers are complete: its cycle has started
            self._disarm()

    def on_response_complete(self) -> None:
        cycle = self.cycle
        super().on_response_complete()
        # the next request's headers get their own deadline, unless a pipelined one has already started
        if self.cycle is cycle and not self.transport.is_closing():
            self._arm()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(self.header_timeout_s, self._expire)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expire(self) -> None:
        self._deadline = None
        if not self.transport.is_closing():
            LOG.warning("request headers not complete within %.1f s (FUZZYRISK_HEADER_TIMEOUT_S): connection closed",
                        self.header_timeout_s, extra={"fields": {"client": "%s:%d" % self.client if self.client
                                                                 else None}})
            self.transport.close()


def protocol(header_timeout_s: float) -> type[HeaderDeadlineProtocol]:
    """The protocol class for ``uvicorn.Config(http=...)`` with this header deadline."""
    return type("HeaderDeadlineProtocol", (HeaderDeadlineProtocol,), {"header_timeout_s": float(header_timeout_s)})
