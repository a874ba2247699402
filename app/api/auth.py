"""The API key check, one function for the middleware that runs it first and the route dependency."""

from __future__ import annotations

import hmac

from pydantic import SecretStr

MISSING = "this service needs an API key: send the header 'Authorization: Bearer <FUZZYRISK_API_KEY>'"
WRONG = "the API key is not the one this service was started with (FUZZYRISK_API_KEY)"
CHALLENGE = 'Bearer realm="fuzzyrisk"'
CHALLENGE_INVALID = 'Bearer realm="fuzzyrisk", error="invalid_token"'


def is_protected(path: str) -> bool:
    """Routes that need the key when one is set: the maps and the planners (not probes, page or docs)."""
    return path == "/maps" or path.startswith("/maps/") or path == "/planners"


def key_error(authorization: str | None, key: SecretStr) -> tuple[str, str] | None:
    """``(detail, WWW-Authenticate)`` when the ``Authorization`` header does not carry ``key``, else None."""
    scheme, _, token = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return MISSING, CHALLENGE
    # constant-time comparison: the time taken must not reveal how much of the key was right
    if not hmac.compare_digest(token.strip().encode(), key.get_secret_value().encode()):
        return WRONG, CHALLENGE_INVALID
    return None
