"""Slow clients against the real server (``python -m app``): request headers trickled byte by byte do not
hold a connection for ever; a client that sends its headers in time is served as before."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any

import pytest

from tests.e2e.conftest import Server

pytestmark = pytest.mark.slow

TIMEOUT_S = 1.0


def _trickle(server: Server, prefix: bytes = b"") -> float:
    """Send ``prefix`` then a header byte every 0.2 s; seconds until the server closes the connection."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        if prefix:
            sock.sendall(prefix)
            assert b"200 OK" in sock.recv(65536)  # the first request is served
        started = time.monotonic()
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")
        sock.settimeout(0.2)
        for _ in range(100):  # 20 s at most
            try:
                sock.sendall(b"X")
                if sock.recv(65536) == b"":
                    return time.monotonic() - started
            except socket.timeout:
                continue
            except (BrokenPipeError, ConnectionResetError):
                return time.monotonic() - started
    return float("inf")


def test_trickled_headers_are_cut_off_and_timely_ones_are_served(start_server: Callable[..., Any]) -> None:
    server = start_server(FUZZYRISK_HEADER_TIMEOUT_S=str(TIMEOUT_S))
    assert TIMEOUT_S <= _trickle(server) < TIMEOUT_S + 3.0
    # on a kept-alive connection, the next request's headers get the same deadline
    keep_alive = b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n"
    assert TIMEOUT_S <= _trickle(server, keep_alive) < TIMEOUT_S + 3.0
    # a request whose headers come in time, however long its answer takes, is not cut off
    with server.client() as client:
        for _ in range(3):
            assert client.get("/health").status_code == 200
            time.sleep(TIMEOUT_S * 1.2)  # idle between requests: uvicorn's keep-alive (5 s) governs that
        assert client.get("/maps").status_code == 200
    assert "FUZZYRISK_HEADER_TIMEOUT_S" in server.log()
