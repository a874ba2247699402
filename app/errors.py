"""Domain errors of the service and the one handler that turns them into HTTP answers.

Services raise these; routes stay free of status codes. Every answer is
``{"detail": ...}`` with a message that says what to change.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from app.storage import StorageUnavailable

LOG = logging.getLogger("fuzzyrisk.storage")
#: What a client is told when the data directory cannot take a write.
STORAGE_UNAVAILABLE_DETAIL = "the data directory is full or read-only; nothing was applied"
#: Seconds a client should wait before retrying a write refused by storage (an operator must act first).
STORAGE_RETRY_AFTER_S = 30


class ServiceError(Exception):
    """Base class: ``status`` is the HTTP status, ``detail`` the JSON detail."""

    status = 500

    def __init__(self, detail: Any, *, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        self.headers = headers


class NotFound(ServiceError):
    status = 404


class Conflict(ServiceError):
    status = 409


class TooLarge(ServiceError):
    status = 413


class InsufficientStorage(ServiceError):
    """507: the service's budget for maps (their number, or their cells together) has no room for this one."""

    status = 507


class UnsupportedMediaType(ServiceError):
    status = 415


class Invalid(ServiceError):
    """422: the request is well-formed but its content cannot be used."""

    status = 422


class PlanRejected(Invalid):
    """422 with ``{"code": <Nav2 name>, "message": ...}``: the start or the goal cannot be used."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__({"code": code, "message": message})


class Unavailable(ServiceError):
    """503: busy or stopping; retry later."""

    status = 503


def _json_safe(value: Any) -> Any:
    """NaN and infinities as strings: the refused input is often exactly such a number."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    return value


def _validation_errors(exc: RequestValidationError) -> list[dict[str, Any]]:
    errors = []
    for error in exc.errors():
        error = dict(error)
        # echo scalars only: the input of a bad scan can be a list of a million ranges
        if isinstance(error.get("input"), (dict, list, bytes)):
            error.pop("input")
        error.pop("url", None)
        errors.append(error)
    return _json_safe(jsonable_encoder(errors))


def install_error_handlers(app: FastAPI) -> None:
    """Answer every ``ServiceError`` as ``{"detail": ...}`` with its status, and 422s without echoing bodies.

    ``StorageUnavailable`` (a full or read-only data directory) answers 503 with ``Retry-After``.
    """

    async def handle(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ServiceError)
        return JSONResponse({"detail": exc.detail}, status_code=exc.status, headers=exc.headers)

    async def handle_validation(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RequestValidationError)
        return JSONResponse({"detail": _validation_errors(exc)}, status_code=422)

    async def handle_storage(request: Request, exc: Exception) -> JSONResponse:
        # the services raise before touching a map in memory, so "nothing was applied" holds
        LOG.error("write refused by storage: %s %s: %s", request.method, request.url.path, exc)
        return JSONResponse(
            {"detail": STORAGE_UNAVAILABLE_DETAIL}, status_code=503,
            headers={"Retry-After": str(STORAGE_RETRY_AFTER_S)},
        )

    app.add_exception_handler(ServiceError, handle)
    app.add_exception_handler(StorageUnavailable, handle_storage)
    app.add_exception_handler(RequestValidationError, handle_validation)
