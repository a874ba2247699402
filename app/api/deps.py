"""Dependencies of the routes, as named ``Annotated`` aliases.

They are ``async def`` although they never await: FastAPI runs a plain ``def`` dependency
in its thread pool, a round trip per dependency per request for a few attribute reads.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.api.auth import key_error
from app.config import Settings
from app.schemas import NAME_PATTERN, NAME_RULE
from app.service.mapservice import MapService

_bearer = HTTPBearer(
    auto_error=False,
    description="Needed only when the service runs with FUZZYRISK_API_KEY set: `Authorization: Bearer <key>`.",
)


async def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings  # type: ignore[no-any-return]


async def get_service(request: Request) -> MapService:
    return request.app.state.service  # type: ignore[no-any-return]


async def require_api_key(
    settings: Annotated[Settings, Depends(get_settings_dep)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """401 unless the request carries the configured bearer token (no check when none is configured).

    ``app.api.middleware.ApiKeyMiddleware`` has already run the same check before the body was
    read; this one declares the scheme in the OpenAPI document and guards a route mounted
    without the middleware.
    """
    if settings.api_key is None:
        return
    header = None if credentials is None else f"{credentials.scheme} {credentials.credentials}"
    error = key_error(header, settings.api_key)
    if error is not None:
        raise HTTPException(status_code=401, detail=error[0], headers={"WWW-Authenticate": error[1]})


ServiceDep = Annotated[MapService, Depends(get_service)]
MapNamePath = Annotated[str, Path(pattern=NAME_PATTERN, description=f"map name: {NAME_RULE}")]
