"""`/openapi.json`, `/docs` (Swagger UI) and `/redoc` from files installed with the service: no CDN.

FastAPI's own pages load their JavaScript from a CDN, so on a robot's offline network they
stay blank. The files come from the ``fastapi-offline`` package (Swagger UI 5, ReDoc); they
are served by explicit routes over a fixed list, as the operator page's are. The schema is a
route of ours too, so that its requests are counted under their route like every other.
"""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import APIRouter, HTTPException, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse

ASSETS_DIR = Path(fastapi_offline.__file__).resolve().parent / "static"
ASSETS_URL = "/docs-assets"
_FILES: dict[str, str] = {
    "swagger-ui-bundle.js": "text/javascript; charset=utf-8",
    "swagger-ui.css": "text/css; charset=utf-8",
    "redoc.standalone.js": "text/javascript; charset=utf-8",
    "favicon.png": "image/png",
}

router = APIRouter(include_in_schema=False)


def _root(request: Request) -> str:
    return str(request.scope.get("root_path", "")).rstrip("/")


@router.get("/openapi.json")
def openapi(request: Request) -> JSONResponse:
    """The OpenAPI 3.1 description of the API (``app.api.factory`` adds the raw-body schemas).

    Behind a path prefix (``root_path``), the prefix is the first server, as FastAPI's own
    route does, so that "Try it out" in ``/docs`` calls the prefixed URLs.
    """
    schema = request.app.openapi()
    root = _root(request)
    servers = list(schema.get("servers", []))
    if root and root not in [s.get("url") for s in servers]:
        schema = {**schema, "servers": [{"url": root}, *servers]}  # a copy: the cached schema stays as it is
    return JSONResponse(schema)


@router.get("/docs")
def swagger_ui(request: Request) -> HTMLResponse:
    """Swagger UI over ``/openapi.json``: every operation, with examples to try."""
    root = _root(request)
    return get_swagger_ui_html(
        openapi_url=f"{root}/openapi.json",
        title="fuzzyrisk - API",
        swagger_js_url=f"{root}{ASSETS_URL}/swagger-ui-bundle.js",
        swagger_css_url=f"{root}{ASSETS_URL}/swagger-ui.css",
        swagger_favicon_url=f"{root}{ASSETS_URL}/favicon.png",
    )


@router.get("/redoc")
def redoc(request: Request) -> HTMLResponse:
    """ReDoc over ``/openapi.json``: the same contract as one readable page."""
    root = _root(request)
    return get_redoc_html(
        openapi_url=f"{root}/openapi.json",
        title="fuzzyrisk - API",
        redoc_js_url=f"{root}{ASSETS_URL}/redoc.standalone.js",
        redoc_favicon_url=f"{root}{ASSETS_URL}/favicon.png",
        with_google_fonts=False,
    )


@router.get(ASSETS_URL + "/{name}")
def asset(name: str) -> FileResponse:
    """One of the pages' files; anything else is 404."""
    media = _FILES.get(name)
    if media is None:
        raise HTTPException(status_code=404, detail=f"no file {name!r}")
    return FileResponse(ASSETS_DIR / name, media_type=media, headers={"Cache-Control": "max-age=86400"})
