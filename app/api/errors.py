"""The handlers that answer every error of the HTTP API with the one ``ErrorBody`` (``app.errors``)."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from app.errors import (
    CLIENT_CLOSED_REQUEST,
    STORAGE_RETRY_AFTER_S,
    VALIDATION_ERROR,
    ServiceError,
    StorageUnavailable,
    error_body,
    error_body_of,
    validation_errors,
    validation_message,
)

LOG = logging.getLogger("fuzzyrisk.storage")


def install_error_handlers(app: FastAPI) -> None:
    """Answer every error with an ``ErrorBody``: services' errors, validation (no bodies echoed),
    Starlette's (unknown route, wrong method), storage refusals (503 + ``Retry-After``) and any
    unexpected exception (500; the server logs its traceback)."""

    async def handle(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ServiceError)
        return JSONResponse(error_body_of(exc), status_code=exc.status, headers=exc.headers)

    async def handle_validation(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RequestValidationError)
        errors = validation_errors(exc)
        return JSONResponse(error_body(VALIDATION_ERROR, validation_message(errors), errors), status_code=422)

    async def handle_http(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, StarletteHTTPException)
        return JSONResponse(error_body_of(exc), status_code=exc.status_code, headers=exc.headers)

    async def handle_storage(request: Request, exc: Exception) -> JSONResponse:
        # the services raise before touching a map in memory, so "nothing was applied" holds
        LOG.error("write refused by storage: %s %s: %s", request.method, request.url.path, exc)
        return JSONResponse(error_body_of(exc), status_code=503, headers={"Retry-After": str(STORAGE_RETRY_AFTER_S)})

    async def handle_disconnect(request: Request, _exc: Exception) -> Response:
        # the client went away while its body arrived: nobody to answer, and nothing went wrong here (it was
        # logged as "Exception in ASGI application" once per such client); 499 as nginx says it
        LOG.info("client disconnected before its body was in: %s %s", request.method, request.url.path)
        return Response(status_code=CLIENT_CLOSED_REQUEST)

    async def handle_unexpected(_request: Request, exc: Exception) -> JSONResponse:
        # Starlette re-raises the exception after this answer: the server logs its traceback once
        return JSONResponse(error_body_of(exc), status_code=500)

    app.add_exception_handler(ServiceError, handle)
    app.add_exception_handler(StorageUnavailable, handle_storage)
    app.add_exception_handler(RequestValidationError, handle_validation)
    app.add_exception_handler(StarletteHTTPException, handle_http)
    app.add_exception_handler(ClientDisconnect, handle_disconnect)
    app.add_exception_handler(Exception, handle_unexpected)
