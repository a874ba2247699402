"""Application factory: ``create_app(settings)`` builds the service; nothing is opened at import time."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.openapi.utils import get_openapi

from app.config import Settings, get_settings
from app.deps import require_api_key
from app.errors import install_error_handlers
from app.metrics import Metrics
from app.middleware import ApiKeyMiddleware, BodyBudgetMiddleware, BodyLimitMiddleware, ObserveMiddleware
from app.routes import docs, maps, plans, risk, scans, system, ui
from app.schemas import RiskGridJSON, ScanBatch
from app.services import MapService
from app.storage import SqliteStorage

LOG = logging.getLogger("fuzzyrisk")
DESCRIPTION = """\
Robots post range scans with their poses; the service fuses them into named fuzzy occupancy
maps (Payeur's fuzzy inference fusion, or a Bayesian baseline) and plans paths whose collision
risk is low and bounded. Metres, radians, REP 103 frames; maps live in the `map` frame.
When the service runs with `FUZZYRISK_API_KEY`, send `Authorization: Bearer <key>`.
"""


def _openapi_with_body_schemas(app: FastAPI) -> dict[str, Any]:
    """OpenAPI plus the schemas that routes reading raw bodies refer to (ScanBatch, RiskGridJSON)."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in (ScanBatch, RiskGridJSON):
            model_schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
            components.update(model_schema.pop("$defs", {}))
            components[model.__name__] = model_schema
        app.openapi_schema = schema
    return app.openapi_schema


def create_app(settings: Settings | None = None) -> FastAPI:
    """The FastAPI application; storage is opened and maps loaded in its lifespan."""
    settings = settings or get_settings()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service = MapService(settings, SqliteStorage(settings.database_path), metrics)
        await service.start()
        app.state.service = service
        LOG.info("answering requests: GET /health says alive, GET /ready says ready for traffic",
                 extra={"fields": {"url": f"http://{settings.host}:{settings.port}"}})
        try:
            yield
        finally:
            # uvicorn has waited for requests in flight (SIGTERM): snapshot and close
            await service.stop()

    # FastAPI's own schema and docs routes off: app/routes/docs.py serves them (pages without a CDN)
    app = FastAPI(title="fuzzyrisk", version="0.1.0", description=DESCRIPTION, lifespan=lifespan,
                  openapi_url=None, docs_url=None, redoc_url=None)
    app.state.settings = settings
    app.state.metrics = metrics
    install_error_handlers(app)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes,
                       small_bytes=settings.max_json_body_bytes)
    app.add_middleware(BodyBudgetMiddleware, max_bytes=settings.max_bodies_in_flight_bytes,
                       read_timeout_s=settings.body_read_timeout_s)
    app.add_middleware(ApiKeyMiddleware, api_key=settings.api_key)  # outside the body limits: the key first
    app.add_middleware(ObserveMiddleware, metrics=metrics)  # added last: outermost, sees every answer

    app.include_router(system.router)
    protected = [Depends(require_api_key)]
    for module in (maps, scans, risk, plans):
        app.include_router(module.router, dependencies=protected)
    app.include_router(ui.router)  # the web page (app/routes/ui.py): its files need no key
    app.include_router(docs.router)  # /docs and /redoc with their files (no CDN), no key
    app.openapi = lambda: _openapi_with_body_schemas(app)  # type: ignore[method-assign]
    return app
