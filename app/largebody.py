"""Responses whose bytes go out a MiB at a time, so that a big read does not hold the event loop while it is sent."""

from __future__ import annotations

from collections.abc import Mapping

from starlette.background import BackgroundTask
from starlette.responses import Response
from starlette.types import Receive, Scope, Send

#: Bytes handed to the server per write. One write of a 16 MB OccupancyGrid was copied into the transport's buffer
#: in one go while every other request waited (issue 11, bench abuse row 10); a MiB is a millisecond or so.
CHUNK_BYTES = 1 << 20


class ChunkedBytesResponse(Response):
    """``Response`` of bytes known in full (``Content-Length`` set as usual), sent in ``CHUNK_BYTES`` pieces."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        await send({"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers})
        body = memoryview(self.body)
        for start in range(0, max(len(body), 1), CHUNK_BYTES):
            end = start + CHUNK_BYTES
            await send({"type": "http.response.body", "body": bytes(body[start:end]), "more_body": end < len(body)})
        if self.background is not None:
            await self.background()


def bytes_response(data: bytes, *, media_type: str, headers: Mapping[str, str] | None = None,
                   background: BackgroundTask | None = None) -> Response:
    """``data`` as a response: in one write when small, a MiB at a time when not."""
    kind = ChunkedBytesResponse if len(data) > CHUNK_BYTES else Response
    return kind(data, media_type=media_type, headers=dict(headers or {}), background=background)
