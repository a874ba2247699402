"""ASGI middleware: the request body limit, and one access-log record and metric per request."""

from __future__ import annotations

import json
import time

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.logs import ACCESS
from app.metrics import Metrics


def _too_large_message(limit: int) -> str:
    return (
        f"request body larger than {limit} bytes (FUZZYRISK_MAX_BODY_BYTES): "
        "split the scans into several batches, or use the binary .npy upload"
    )


class BodyLimitMiddleware:
    """Answer 413 once a body exceeds ``max_bytes``: at once from Content-Length, else while reading.

    The check is made on the bytes as they arrive, so a client that lies about (or omits)
    Content-Length cannot make the service buffer more than the limit.
    """

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            body = json.dumps({"detail": _too_large_message(self.max_bytes)}).encode()
            await send(
                {
                    "type": "http.response.start",
                    "status": 413,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
                }
            )
            await send({"type": "http.response.body", "body": body})
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    # an HTTPException: FastAPI's body parsing re-raises it and the exception
                    # middleware answers {"detail": ...} with 413
                    raise HTTPException(status_code=413, detail=_too_large_message(self.max_bytes))
            return message

        await self.app(scope, limited_receive, send)


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
