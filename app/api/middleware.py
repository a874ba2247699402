"""ASGI middleware: the API key before anything else, the request body limits, and one access-log
record and metric per request."""

from __future__ import annotations

import asyncio
import json
import math
import re
import time

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from pydantic import SecretStr

from app.api.auth import is_protected, key_error
from app.errors import error_body, status_code_name
from app.ops.logs import ACCESS
from app.ops.metrics import Metrics

#: The routes whose bodies may be large (scan and bag uploads, a saved map imported): every other body gets the
#: small limit.
UPLOAD_PATH = re.compile(r"^/maps/(import|[^/]+/(scans|bags))$")


def _too_large_message(limit: int, setting: str, path: str) -> str:
    if path == "/maps/import":
        advice = "send the map as a zip or a PNG (compressed), or at a coarser resolution"
    elif UPLOAD_PATH.match(path):
        advice = "split the scans into several batches, or use the binary .npy upload"
    else:
        advice = "split the request"
    return f"request body larger than {limit} bytes ({setting}): {advice}"


async def _answer(send: Send, status: int, message: str, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    body = json.dumps(error_body(status_code_name(status), message)).encode()
    await send({
        "type": "http.response.start",
        "status": status,
        "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                    *(headers or [])],
    })
    await send({"type": "http.response.body", "body": body})


class ApiKeyMiddleware:
    """401 for a protected route without the configured key, before a byte of its body is read.

    A route dependency would run only after FastAPI parsed the body: a 66 MB JSON body with a
    wrong key was parsed (10 s, +1 GB) before its 401.
    """

    def __init__(self, app: ASGIApp, api_key: SecretStr | None) -> None:
        self.app = app
        self.api_key = api_key

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if self.api_key is not None and scope["type"] == "http" and is_protected(scope["path"]):
            header = dict(scope["headers"]).get(b"authorization")
            error = key_error(None if header is None else header.decode("latin-1"), self.api_key)
            if error is not None:
                await _answer(send, 401, error[0], [(b"www-authenticate", error[1].encode())])
                return
        await self.app(scope, receive, send)


class BodyLimitMiddleware:
    """Answer 413 once a body exceeds its limit: at once from Content-Length, else while reading.

    Uploads (``UPLOAD_PATH``) may carry ``max_bytes``, every other route ``small_bytes``
    (a risk query's points, a map, a plan). The check is made on the bytes as they arrive, so a
    client that lies about (or omits) Content-Length cannot make the service buffer more.
    """

    def __init__(self, app: ASGIApp, max_bytes: int, small_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.small_bytes = small_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        upload = bool(UPLOAD_PATH.match(scope["path"]))
        if upload or self.max_bytes <= self.small_bytes:
            limit, setting = self.max_bytes, "FUZZYRISK_MAX_BODY_BYTES"
        else:
            limit, setting = self.small_bytes, "FUZZYRISK_MAX_JSON_BODY_BYTES"
        too_large = _too_large_message(limit, setting, scope["path"])
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await _answer(send, 413, too_large)
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    # an HTTPException: FastAPI's body parsing re-raises it and the exception
                    # middleware answers it with 413 and the error body
                    raise HTTPException(status_code=413, detail=too_large)
            return message

        await self.app(scope, limited_receive, send)


class BodyBudgetMiddleware:
    """Bodies in flight, counted from their first byte: a budget for all of them, and a read timeout.

    Every request's body bytes count from the moment they arrive until the request is answered
    (the service holds a parsed body that long); a chunk that would take all bodies together past
    ``max_bytes`` answers 503 with ``Retry-After``, so forty slow 60 MB uploads cannot take 2.6 GB.
    A body whose next chunk takes longer than ``read_timeout_s``, or which is not all
    in within ``body_timeout_s`` of its first wait, answers 408: a trickled body (a byte every 10 s
    passes any per-chunk timeout) does not hold its connection and its share of the budget for ever.
    The bodies of one map hold at most half the budget once two of them are arriving: forty
    uploads to one map took all of it, and every other map's scans answered 503 for a second at
    a time (bench abuse row 3). One body alone may still take the whole budget.
    """

    def __init__(self, app: ASGIApp, max_bytes: int, read_timeout_s: float, body_timeout_s: float = math.inf) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.read_timeout_s = read_timeout_s
        self.body_timeout_s = body_timeout_s
        self.in_flight = 0  # bytes of bodies received and not yet answered (one event loop: no lock)
        self.by_map: dict[str, int] = {}  # the same, by the map the request's path names ("" for others)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        held = 0
        body_done = False
        deadline: float | None = None  # the whole body's, from the first wait for it
        target = _map_of(scope.get("path", ""))

        async def budgeted_receive() -> Message:
            nonlocal held, body_done, deadline
            if body_done:  # after the body only a disconnect can come: no timeout on that wait
                return await receive()
            now = time.monotonic()
            if deadline is None:
                deadline = now + self.body_timeout_s
            wait = min(self.read_timeout_s, deadline - now)
            try:
                message = await asyncio.wait_for(receive(), max(wait, 0.0))
            except asyncio.TimeoutError:
                if wait < self.read_timeout_s:
                    raise HTTPException(status_code=408, detail=(
                        f"the request body took more than {self.body_timeout_s:g} s "
                        "(FUZZYRISK_BODY_TIMEOUT_S): send it faster, or smaller")) from None
                raise HTTPException(status_code=408, detail=(
                    f"the request body stalled: no bytes for {self.read_timeout_s:g} s "
                    "(FUZZYRISK_BODY_READ_TIMEOUT_S)")) from None
            if message["type"] == "http.request":
                size = len(message.get("body", b""))
                if self.in_flight + size > self.max_bytes:
                    raise HTTPException(status_code=503, headers={"Retry-After": "1"}, detail=(
                        f"the service is receiving {self.in_flight} bytes of request bodies, its limit "
                        f"(FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES); retry"))
                mine = self.by_map.get(target, 0)
                if mine > held and mine + size > self.max_bytes // 2:
                    raise HTTPException(status_code=503, headers={"Retry-After": "1"}, detail=(
                        f"map {target!r} is receiving {mine} bytes of request bodies, the most one map's "
                        f"may hold while others arrive (half of FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES); retry"))
                self.in_flight += size
                self.by_map[target] = mine + size
                held += size
                body_done = not message.get("more_body", False)
            else:
                body_done = True
            return message

        try:
            await self.app(scope, budgeted_receive, send)
        finally:
            self.in_flight -= held
            if held:
                left = self.by_map[target] - held
                if left:
                    self.by_map[target] = left
                else:
                    del self.by_map[target]


def _map_of(path: str) -> str:
    """The map a request's path names (``/maps/{name}/...``), or "" for any other path."""
    parts = path.split("/", 3)
    return parts[2] if len(parts) > 2 and parts[1] == "maps" else ""


class ObserveMiddleware:
    """Log one ``access`` record per request (method, path, route, status, duration) and count it."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500

        async def observing_send(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, observing_send)
        finally:
            duration = time.perf_counter() - started
            route_obj = scope.get("route")
            # the route template, not the raw path, keeps the metric's label set small
            route = getattr(route_obj, "path", None) or "unmatched"
            method = scope["method"]
            self.metrics.requests.labels(method, route, str(status)).inc()
            self.metrics.request_seconds.labels(method, route).observe(duration)
            client = scope.get("client")
            ACCESS.info(
                "request",
                extra={
                    "fields": {
                        "method": method,
                        "path": scope["path"],
                        "route": route,
                        "status": status,
                        "duration_ms": round(duration * 1000.0, 2),
                        "client": client[0] if client else None,
                    }
                },
            )
