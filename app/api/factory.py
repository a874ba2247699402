"""Application factory: ``create_app(settings)`` builds the service; nothing is opened at import time."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.openapi.utils import get_openapi

from app.service import bag_upload
from app.config import Settings, get_settings
from app.api.deps import require_api_key
from app.api.auth import is_protected
from app.api.errors import install_error_handlers
from app.errors import ErrorBody
from app.ops.metrics import Metrics
from app.ops.version import package_version
from app.api.middleware import ApiKeyMiddleware, BodyBudgetMiddleware, BodyLimitMiddleware, ObserveMiddleware
from app.api.routes import bags, docs, maps, plans, recordings, risk, scans, system, trajectory, ui
from app.schemas import CorrectedPath, OccupancyGridMessage, RiskGridJSON, ScanBatch
from app.service.mapservice import MapService
from app.storage import SqliteStorage, Storage

LOG = logging.getLogger("fuzzyrisk")
DESCRIPTION = """\
Robots post range scans with their poses; the service fuses them into named fuzzy occupancy
maps (Payeur's fuzzy inference fusion, or a Bayesian baseline) and plans paths whose collision
risk is low and bounded. Metres, radians, REP 103 frames; each map lives in its own frame
(`frame_id`, `map` unless created otherwise).
When the service runs with `FUZZYRISK_API_KEY`, send `Authorization: Bearer <key>`.
"""


#: Errors any operation can answer, whatever its route says (middleware, validation, the unexpected).
_COMMON_ERRORS = {
    "500": "an unexpected error (the service's log has the traceback)",
}
#: ... and those of the operations behind the API key, and of those with a request body.
_KEY_ERRORS = {"401": "FUZZYRISK_API_KEY is set and the request does not carry it (Authorization: Bearer)"}
_BODY_ERRORS = {
    "400": "the body could not be read as its Content-Type says (code BAD_REQUEST)",
    "408": "the body stalled (FUZZYRISK_BODY_READ_TIMEOUT_S)",
    "413": "the body is larger than FUZZYRISK_MAX_JSON_BODY_BYTES (scan and bag uploads: "
           "FUZZYRISK_MAX_BODY_BYTES)",
    "503": "the bodies in flight fill FUZZYRISK_MAX_BODIES_IN_FLIGHT_BYTES, or the service is busy (Retry-After)",
}
#: ... and those of the operations on one map.
_MAP_ERRORS = {
    "404": "no map of that name",
    "503": "the map is quarantined: its stored rows are damaged (GET /ready lists it)",
}
_ERROR_REF = {"$ref": "#/components/schemas/ErrorBody"}


def _declare_errors(schema: dict[str, Any]) -> None:
    """Every operation declares its error answers, each an ``ErrorBody`` (the one error shape).

    Routes name the errors of their own (409, 415, 507...); added here where a route does not:
    422 where there is input, the key's 401, the body's 400 and its limits' 408/413/503, a map's
    404 and 503 (quarantined), and 500. FastAPI's own validation error schemas go: the service
    never answers them.
    """
    for path, item in schema.get("paths", {}).items():
        for operation in item.values():
            responses = operation.setdefault("responses", {})
            extra = dict(_COMMON_ERRORS)
            if is_protected(path):
                extra.update(_KEY_ERRORS)
            if "requestBody" in operation:
                extra.update(_BODY_ERRORS)
            if path.startswith("/maps/{name}"):
                extra.update(_MAP_ERRORS)
            if operation.get("parameters") or "requestBody" in operation:
                extra["422"] = "the request does not match this operation's schema (code VALIDATION_ERROR)"
            for status, description in extra.items():
                responses.setdefault(status, {"description": description})
            for status, response in responses.items():
                if status[0] not in "45":
                    continue
                content = response.setdefault("content", {})
                json_body = content.get("application/json", {}).get("schema", {})
                if "HTTPValidationError" in json_body.get("$ref", "") or not json_body:
                    content["application/json"] = {"schema": dict(_ERROR_REF)}
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    for name in ("HTTPValidationError", "ValidationError"):
        components.pop(name, None)
    components["ErrorBody"] = ErrorBody.model_json_schema(ref_template="#/components/schemas/{model}")


def _openapi_with_body_schemas(app: FastAPI) -> dict[str, Any]:
    """OpenAPI plus the schemas that routes reading raw bodies refer to (ScanBatch, RiskGridJSON, OccupancyGridMessage,
    CorrectedPath), and
    every operation's error answers declared with the one error body."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in (ScanBatch, RiskGridJSON, OccupancyGridMessage, CorrectedPath):
            model_schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
            components.update(model_schema.pop("$defs", {}))
            components[model.__name__] = model_schema
        _declare_errors(schema)
        app.openapi_schema = schema
    return app.openapi_schema


async def _start_live_view(settings: Settings, service: MapService) -> Any:
    """The Foxglove live view (``app.reads.foxglove``) when configured; the module and its SDK are imported only then."""
    if settings.foxglove_port is None:
        return None
    try:
        from app.reads import foxglove

        return foxglove.attach(service, host=settings.foxglove_host, port=settings.foxglove_port,
                                    interval_s=settings.foxglove_interval_s, max_cells=settings.foxglove_max_cells,
                                    loop=asyncio.get_running_loop())
    except BaseException as exc:
        LOG.error("cannot start: %s", exc)
        await service.stop()
        raise


def open_storage(settings: Settings) -> Storage:
    """PostgreSQL when ``FUZZYRISK_DATABASE_URL`` is set (replicas share it), else SQLite in the data directory."""
    if settings.database_url is None:
        return SqliteStorage(settings.database_path)
    from app.storage.postgres import PostgresStorage  # psycopg is needed (and imported) only then

    return PostgresStorage(settings.database_url.get_secret_value())


async def _build_routes(app: FastAPI) -> None:
    """Have FastAPI build every route's parameters now rather than at the first request that reaches them.

    FastAPI (0.16x) builds an included router's routes, their parameters and models, at its first
    request: about 140 ms holding the GIL, every other request waiting. A request for a
    path no route takes, sent to the router alone (no middleware, no handler), walks them all.
    """
    scope = {"type": "http", "method": "GET", "path": "/maps/-/-/-/-/-/-/-", "raw_path": b"/maps/-/-/-/-/-/-/-",
             "root_path": "", "query_string": b"", "headers": [], "scheme": "http", "http_version": "1.1",
             "server": None, "client": None}  # without "app", the router answers 404 itself instead of raising

    async def receive() -> dict[str, Any]:
        return {"type": "http.disconnect"}

    async def send(message: dict[str, Any]) -> None:
        pass

    await app.router(scope, receive, send)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The FastAPI application; storage is opened and maps loaded in its lifespan."""
    settings = settings or get_settings()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service = MapService(settings, await asyncio.to_thread(open_storage, settings), metrics)
        await asyncio.to_thread(bag_upload.remove_leftovers, settings.temp_dir)  # a killed run's uploads
        await service.start()
        try:
            await _build_routes(app)
        except Exception:  # noqa: BLE001 - an optimisation of the first requests: never a reason not to start
            LOG.warning("the routes could not be built ahead of the first requests", exc_info=True)
        live = await _start_live_view(settings, service)  # None unless FUZZYRISK_FOXGLOVE_PORT is set
        app.state.service = service
        LOG.info("answering requests: GET /health says alive, GET /ready says ready for traffic",
                 extra={"fields": {"url": f"http://{settings.host}:{settings.port}"}})
        try:
            yield
        finally:
            # uvicorn has waited for requests in flight (SIGTERM): snapshot and close
            if live is not None:  # first: its publisher thread reads grids through the service
                await asyncio.to_thread(live.close)
            await service.stop()

    # FastAPI's own schema and docs routes off: app/routes/docs.py serves them (pages without a CDN)
    # operation ids are the route functions' names (create_map, post_scans, plan...): what generated
    # clients name their functions after, instead of FastAPI's create_map_maps_post
    app = FastAPI(title="fuzzyrisk", version=package_version(), description=DESCRIPTION, lifespan=lifespan,
                  openapi_url=None, docs_url=None, redoc_url=None,
                  generate_unique_id_function=lambda route: route.name)
    app.state.settings = settings
    app.state.metrics = metrics
    install_error_handlers(app)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes,
                       small_bytes=settings.max_json_body_bytes)
    app.add_middleware(BodyBudgetMiddleware, max_bytes=settings.max_bodies_in_flight_bytes,
                       read_timeout_s=settings.body_read_timeout_s, body_timeout_s=settings.body_timeout_s)
    app.add_middleware(ApiKeyMiddleware, api_key=settings.api_key)  # outside the body limits: the key first
    app.add_middleware(ObserveMiddleware, metrics=metrics)  # added last: outermost, sees every answer

    app.include_router(system.router)
    protected = [Depends(require_api_key)]
    for module in (maps, scans, bags, risk, recordings, trajectory, plans):
        app.include_router(module.router, dependencies=protected)
    app.include_router(ui.router)  # the web page (app/routes/ui.py): its files need no key
    app.include_router(docs.router)  # /docs and /redoc with their files (no CDN), no key
    app.openapi = lambda: _openapi_with_body_schemas(app)  # type: ignore[method-assign]
    return app
