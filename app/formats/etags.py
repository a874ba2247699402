"""Conditional reads of a map's grids: a strong ETag per map version and representation, 304 on a match.

A grid read is a pure function of the map (its stored creation parameters, which include its
frame), its version, and the representation asked for (the route and its query). Stamps in
the bodies are the time of the map's last batch, not of the read, so every read of one
version gives the same bytes and the tag can be strong. The tag is a digest of those inputs,
known before any work: a matching ``If-None-Match`` answers 304 without reading the grid.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any

from fastapi import Response

#: The response header that carries the map version on every read of one map.
VERSION_HEADER = "X-Map-Version"


def map_seed(meta: Mapping[str, Any]) -> str:
    """What tells two maps of one name apart (a map deleted and created again restarts at version 0)."""
    return hashlib.blake2b(json.dumps(meta, sort_keys=True, default=str).encode(), digest_size=16).hexdigest()


def entity_tag(seed: str, version: int, variant: Mapping[str, Any]) -> str:
    """A strong ETag: ``"v<version>-<digest of the map, the version and the representation>"``."""
    text = json.dumps([seed, version, sorted(variant.items())], default=repr, separators=(",", ":"))
    return f'"v{version}-{hashlib.blake2b(text.encode(), digest_size=12).hexdigest()}"'


def matches(if_none_match: str | None, etag: str) -> bool:
    """Does an ``If-None-Match`` header match ``etag``? (RFC 9110 13.1.2: ``*``, a list, weak comparison.)"""
    if not if_none_match:
        return False
    if if_none_match.strip() == "*":
        return True
    ours = etag.removeprefix("W/")
    return any(tag.strip().removeprefix("W/") == ours for tag in if_none_match.split(","))


def not_modified(etag: str, version: int) -> Response:
    """304 with no body, and the headers a 200 would have carried for caches (RFC 9110 15.4.5)."""
    return Response(status_code=304, headers={"ETag": etag, VERSION_HEADER: str(version)})
