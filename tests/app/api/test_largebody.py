"""Big response bodies go out a MiB at a time (one 16 MB write held the event loop)."""

from __future__ import annotations

import asyncio
import os

from app.api.largebody import CHUNK_BYTES, ChunkedBytesResponse, bytes_response


def _sent(response: object) -> list[dict]:
    messages: list[dict] = []

    async def receive() -> dict:
        return {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        messages.append(message)

    asyncio.run(response({"type": "http", "method": "GET", "path": "/"}, receive, send))  # type: ignore[operator]
    return messages


def test_a_big_body_is_sent_in_pieces_whole_and_with_its_length() -> None:
    data = os.urandom(2 * CHUNK_BYTES + 123)
    response = bytes_response(data, media_type="application/octet-stream", headers={"ETag": '"v1"'})
    assert isinstance(response, ChunkedBytesResponse)
    messages = _sent(response)
    start, bodies = messages[0], messages[1:]
    headers = dict(start["headers"])
    assert start["status"] == 200 and headers[b"content-length"] == str(len(data)).encode()
    assert headers[b"etag"] == b'"v1"' and headers[b"content-type"] == b"application/octet-stream"
    assert [len(m["body"]) for m in bodies] == [CHUNK_BYTES, CHUNK_BYTES, 123]
    assert [m["more_body"] for m in bodies] == [True, True, False]
    assert b"".join(m["body"] for m in bodies) == data


def test_a_small_body_is_one_write() -> None:
    messages = _sent(bytes_response(b"abc", media_type="text/plain"))
    assert [m.get("body") for m in messages[1:]] == [b"abc"]


def test_a_body_in_pieces_is_sent_as_their_bytes_in_order_never_joined_beyond_a_chunk() -> None:
    import numpy as np

    head, cells = b"head", np.arange(3 * CHUNK_BYTES // 2, dtype=np.int64).astype(np.int8)
    response = bytes_response((head, b"", memoryview(cells)), media_type="application/octet-stream")
    messages = _sent(response)
    bodies = messages[1:]
    assert dict(messages[0]["headers"])[b"content-length"] == str(len(head) + cells.nbytes).encode()
    assert [len(m["body"]) for m in bodies] == [len(head), CHUNK_BYTES, cells.nbytes - CHUNK_BYTES]
    assert [m["more_body"] for m in bodies] == [True, True, False]
    assert b"".join(m["body"] for m in bodies) == head + cells.tobytes()


def test_an_empty_body_in_pieces_is_one_empty_write() -> None:
    messages = _sent(bytes_response((b"",), media_type="text/plain"))
    assert dict(messages[0]["headers"])[b"content-length"] == b"0"
    assert [(m["body"], m["more_body"]) for m in messages[1:]] == [(b"", False)]
