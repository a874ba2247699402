"""Responses whose bytes go out a MiB at a time, so that a big read does not hold the event loop while it is sent."""

from __future__ import annotations

from collections.abc import Callable, Mapping

from starlette.background import BackgroundTask
from starlette.responses import Response
from starlette.types import Receive, Scope, Send

#: Bytes handed to the server per write. One write of a 16 MB OccupancyGrid was copied into the transport's buffer
#: in one go while every other request waited (bench abuse row 10); a MiB is a millisecond or so.
CHUNK_BYTES = 1 << 20


#: A body: bytes, or its pieces in order (sent as they are, never joined: joining 16 MB held the GIL)
Body = bytes | tuple[bytes | memoryview, ...]


class ChunkedBytesResponse(Response):
    """A body known in full (``Content-Length`` set), given whole or in pieces, sent in ``CHUNK_BYTES`` writes.

    ``on_sent`` is called once the body is sent, or its sending failed (the client went away): a big read's
    turn in ``app.reads.lane`` lasts until then.
    """

    def __init__(self, content: Body, status_code: int = 200, headers: Mapping[str, str] | None = None,
                 media_type: str | None = None, background: BackgroundTask | None = None,
                 on_sent: Callable[[], None] | None = None) -> None:
        self.on_sent = on_sent
        self.parts = [memoryview(p).cast("B") for p in ((content,) if isinstance(content, bytes) else content)]
        self.status_code = status_code
        self.media_type = media_type
        self.background = background
        self.body = b""  # what Response keeps; the parts are what is sent
        self.init_headers({**(headers or {}), "content-length": str(sum(p.nbytes for p in self.parts))})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await send({"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers})
            pieces = [part[start:start + CHUNK_BYTES] for part in self.parts if part.nbytes
                      for start in range(0, part.nbytes, CHUNK_BYTES)]
            if not pieces:
                await send({"type": "http.response.body", "body": b"", "more_body": False})
            for i, piece in enumerate(pieces):
                await send({"type": "http.response.body", "body": bytes(piece), "more_body": i < len(pieces) - 1})
        finally:
            if self.on_sent is not None:
                self.on_sent()
        if self.background is not None:
            await self.background()


def bytes_response(data: Body, *, media_type: str, headers: Mapping[str, str] | None = None,
                   background: BackgroundTask | None = None, on_sent: Callable[[], None] | None = None) -> Response:
    """``data`` as a response: in one write when small, a MiB at a time when not; ``on_sent`` as
    ``ChunkedBytesResponse``'s."""
    if isinstance(data, bytes) and len(data) <= CHUNK_BYTES and on_sent is None:
        return Response(data, media_type=media_type, headers=dict(headers or {}), background=background)
    return ChunkedBytesResponse(data, media_type=media_type, headers=headers, background=background,
                                on_sent=on_sent)
