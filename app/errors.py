"""Domain errors of the service and the one error body every answer uses (``app.api.errors`` installs the handlers).

Services raise these; routes stay free of status codes. Every error answer, whoever writes it
(a service, request validation, the middleware, an unknown route, an unexpected exception), is
an ``ErrorBody``: ``{"code": ..., "message": ..., "details": ...}``. ``code`` is stable and
machine-readable (Nav2's ``ComputePathToPose`` names for a start or goal a plan cannot use),
``message`` says what to change, ``details`` carries structure where there is some (the list
of validation errors) and is ``null`` otherwise.
"""

from __future__ import annotations

import http
import math
from typing import Any

from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

#: What a client is told when the data directory cannot take a write.
STORAGE_UNAVAILABLE_DETAIL = ("the map store cannot take the write (the data directory full or read-only, or the "
                              "database unreachable); nothing was applied")
#: ... when the database connection was lost while it committed (``CommitUncertain``).
COMMIT_UNCERTAIN_DETAIL = ("the database's commit was cut short (its connection lost, or a disk error at the commit): "
                           "the batch may be stored; read the map's version before sending it again")
#: Seconds a client should wait before retrying a write refused by storage (an operator must act first).
STORAGE_RETRY_AFTER_S = 30

#: The code of an error answer by its status, where nothing more specific is known.
STATUS_CODES: dict[int, str] = {
    400: "BAD_REQUEST",
    401: "UNAUTHORIZED",
    403: "FORBIDDEN",
    404: "NOT_FOUND",
    405: "METHOD_NOT_ALLOWED",
    408: "REQUEST_TIMEOUT",
    409: "CONFLICT",
    413: "TOO_LARGE",
    415: "UNSUPPORTED_MEDIA_TYPE",
    422: "INVALID",
    429: "TOO_MANY_REQUESTS",
    500: "INTERNAL_ERROR",
    503: "UNAVAILABLE",
    507: "INSUFFICIENT_STORAGE",
}
#: The status logged for a request whose client went away before its body was in (nginx's; never received).
CLIENT_CLOSED_REQUEST = 499
#: The code of a request that does not match the operation's schema (``details``: one entry per problem).
VALIDATION_ERROR = "VALIDATION_ERROR"
STORAGE_UNAVAILABLE = "STORAGE_UNAVAILABLE"


class ErrorBody(BaseModel):
    """The body of every error answer."""

    code: str = Field(description="stable, machine-readable: INVALID, NOT_FOUND, VALIDATION_ERROR, ..., or "
                                  "a Nav2 ComputePathToPose error name (START_OCCUPIED, GOAL_OUTSIDE_MAP, ...)")
    message: str = Field(description="what went wrong and what to change, for a person")
    details: Any = Field(None, description="structured detail where there is some (VALIDATION_ERROR: the list "
                                           "of problems, each with loc, msg, type), else null")


def status_code_name(status: int) -> str:
    """The ``code`` of an error answer with this HTTP status and nothing more specific to say."""
    if status in STATUS_CODES:
        return STATUS_CODES[status]
    try:
        return http.HTTPStatus(status).name
    except ValueError:
        return "ERROR"


def error_body(code: str, message: str, details: Any = None) -> dict[str, Any]:
    """An ``ErrorBody`` as a JSON-ready dict (NaN and infinities in ``details`` as strings)."""
    return {"code": code, "message": message, "details": _json_safe(details)}


class ServiceError(Exception):
    """Base class: ``status`` is the HTTP status; the answer is ``ErrorBody(code, message, details)``.

    ``code`` defaults to the status's (``STATUS_CODES``); ``details`` to null.
    """

    status = 500

    def __init__(self, message: str, *, code: str | None = None, details: Any = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.message = str(message)
        self.code = code or status_code_name(self.status)
        self.details = details
        self.headers = headers

    def __reduce__(self) -> tuple[Any, ...]:
        # pickled as it was made (a parse process raises these): Exception's own pickling keeps only the message
        return _rebuild, (type(self), self.message, self.code, self.details, self.headers)


def _rebuild(cls: type[ServiceError], message: str, code: str, details: Any,
             headers: dict[str, str] | None) -> ServiceError:
    error = cls.__new__(cls)
    ServiceError.__init__(error, message, code=code, details=details, headers=headers)
    return error


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
    """422 whose ``code`` is Nav2's name for why (``START_OCCUPIED``, ``GOAL_OUTSIDE_MAP``, ...): the start
    or the goal cannot be used."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message, code=code)


class Unavailable(ServiceError):
    """503: busy or stopping; retry later."""

    status = 503


class StorageUnavailable(Exception):
    """A write could not be made durable (disk full, read-only or failing data directory, database unreachable);
    nothing was stored."""


class CommitUncertain(StorageUnavailable):
    """The connection to the database was lost while it committed (or SQLite's disk failed at the commit): the
    write may be stored, or not.

    Never retried by the service (a retry could store it twice); the client is told to check.
    """


def _json_safe(value: Any) -> Any:
    """NaN and infinities as strings: the refused input is often exactly such a number."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    return value


def validation_errors(exc: RequestValidationError) -> list[dict[str, Any]]:
    errors = []
    for error in exc.errors():
        error = dict(error)
        # echo scalars only: the input of a bad scan can be a list of a million ranges
        if isinstance(error.get("input"), (dict, list, bytes)):
            error.pop("input")
        error.pop("url", None)
        errors.append(error)
    return _json_safe(jsonable_encoder(errors))  # type: ignore[no-any-return]


def validation_message(errors: list[dict[str, Any]]) -> str:
    """The first problems in one line: ``body.scans.0.ranges: Input should be ... (and 3 more)``."""
    parts = [f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg', '')}" for e in errors[:3]]
    more = f" (and {len(errors) - 3} more)" if len(errors) > 3 else ""
    return ("; ".join(parts) + more) if parts else "the request does not match the operation's schema"


def error_body_of(exc: BaseException) -> dict[str, Any]:
    """The ``ErrorBody`` of ``exc``, as a dict: what the handlers below answer with, and what a bag import that
    stopped part-way tells inside its 200."""
    if isinstance(exc, ServiceError):
        return error_body(exc.code, exc.message, exc.details)
    if isinstance(exc, CommitUncertain):
        return error_body(STORAGE_UNAVAILABLE, COMMIT_UNCERTAIN_DETAIL)
    if isinstance(exc, StorageUnavailable):
        return error_body(STORAGE_UNAVAILABLE, STORAGE_UNAVAILABLE_DETAIL)
    if isinstance(exc, StarletteHTTPException):
        return error_body(status_code_name(exc.status_code), str(exc.detail))
    return error_body(status_code_name(500), f"internal error ({type(exc).__name__}); nothing more is told here: "
                      "the service's log has the traceback")
