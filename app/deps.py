"""Dependencies of the routes, as named ``Annotated`` aliases.

They are ``async def`` although they never await: FastAPI runs a plain ``def`` dependency
in its thread pool, a round trip per dependency per request for a few attribute reads.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.config import Settings
from app.schemas import NAME_PATTERN, NAME_RULE
from app.services import MapService

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
    """401 unless the request carries the configured bearer token (no check when none is configured)."""
    if settings.api_key is None:
        return
    if credentials is None:
        raise HTTPException(
            status_code=401,
            detail="this service needs an API key: send the header 'Authorization: Bearer <FUZZYRISK_API_KEY>'",
            headers={"WWW-Authenticate": 'Bearer realm="fuzzyrisk"'},
        )
    # constant-time comparison: the time taken must not reveal how much of the key was right
    if not hmac.compare_digest(credentials.credentials.encode(), settings.api_key.get_secret_value().encode()):
        raise HTTPException(
            status_code=401,
            detail="the API key is not the one this service was started with (FUZZYRISK_API_KEY)",
            headers={"WWW-Authenticate": 'Bearer realm="fuzzyrisk", error="invalid_token"'},
        )


ServiceDep = Annotated[MapService, Depends(get_service)]
MapNamePath = Annotated[str, Path(pattern=NAME_PATTERN, description=f"map name: {NAME_RULE}")]
