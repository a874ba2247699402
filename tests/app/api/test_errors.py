"""One error body for every error: whoever answers, the client reads ``{code, message,
details}``, and the OpenAPI document declares that body for every status the operation can answer."""

from __future__ import annotations

import asyncio
import re
from collections.abc import Callable
from typing import Any

import pytest
from fastapi import FastAPI, Request
from fastapi.testclient import TestClient

from app.api.errors import install_error_handlers
from app.errors import CLIENT_CLOSED_REQUEST
from app.api.factory import create_app

KEY = "key-for-the-error-tests-0123456789"
ERROR_REF = "#/components/schemas/ErrorBody"


def _assert_error(response: Any, status: int, code: str) -> dict[str, Any]:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/json"
    body = response.json()
    assert set(body) == {"code", "message", "details"}, body
    assert body["code"] == code, body
    assert isinstance(body["message"], str) and body["message"], body
    return body  # type: ignore[no-any-return]


def _declared(client: TestClient, method: str, template: str, status: int) -> None:
    """The operation declares ``status`` with the error body."""
    operation = client.get("/openapi.json").json()["paths"][template][method.lower()]
    response = operation["responses"][str(status)]
    assert response["content"]["application/json"]["schema"] == {"$ref": ERROR_REF}


@pytest.mark.parametrize(
    ("method", "path", "template", "kwargs", "status", "code"),
    [
        ("GET", "/maps/nope", "/maps/{name}", {}, 404, "NOT_FOUND"),
        ("POST", "/maps", "/maps", {"json": {"name": "lab", "resolution": 0.1, "origin": [0, 0], "size": [1, 1]}},
         409, "CONFLICT"),
        ("POST", "/maps", "/maps", {"json": {"name": "x", "resolution": "fine"}}, 422, "VALIDATION_ERROR"),
        ("POST", "/maps/lab/scans", "/maps/{name}/scans", {"content": b"\x00" * 8}, 415, "UNSUPPORTED_MEDIA_TYPE"),
        ("GET", "/maps/lab/risk", "/maps/{name}/risk", {"params": {"format": "png", "layer": "observed"}}, 422,
         "INVALID"),
        ("POST", "/maps/lab/plan", "/maps/{name}/plan", {"json": {"start": [-9, 0], "goal": [1, 1]}}, 422,
         "START_OUTSIDE_MAP"),
        ("POST", "/maps/lab/risk/query", "/maps/{name}/risk/query",
         {"content": b"[" * 9_000_000, "headers": {"Content-Type": "application/json"}}, 413, "TOO_LARGE"),
        ("POST", "/maps/import?name=lab", "/maps/import", {"content": b"PK", "headers": {"Content-Type": "application/zip"}},
         409, "CONFLICT"),
        ("POST", "/maps/import?name=new", "/maps/import", {"content": b"PK", "headers": {"Content-Type": "application/zip"}},
         422, "INVALID"),
        ("POST", "/maps/import?name=new", "/maps/import", {"content": b"PK", "headers": {"Content-Type": "image/png"}},
         415, "UNSUPPORTED_MEDIA_TYPE"),
    ],
)
def test_every_error_has_the_one_body_and_is_declared(lab: TestClient, method: str, path: str, template: str,
                                                      kwargs: dict[str, Any], status: int, code: str) -> None:
    _assert_error(lab.request(method, path, **kwargs), status, code)
    _declared(lab, method, template, status)


def test_a_schema_mismatch_lists_every_problem_in_details(lab: TestClient) -> None:
    body = _assert_error(lab.post("/maps/lab/plan", json={"start": [0, "a"], "goal": None}), 422, "VALIDATION_ERROR")
    locations = [tuple(problem["loc"]) for problem in body["details"]]
    assert ("body", "start", 1) in locations and ("body", "goal") in locations
    assert "body.start.1" in body["message"] and "body.goal" in body["message"]


def test_errors_starlette_answers_have_the_body_too(lab: TestClient) -> None:
    _assert_error(lab.get("/no/such/route"), 404, "NOT_FOUND")
    _assert_error(lab.put("/maps/lab"), 405, "METHOD_NOT_ALLOWED")


def test_the_api_key_answer_has_the_body_and_is_declared(make_client: Callable[..., TestClient]) -> None:
    locked = make_client(api_key=KEY)
    _assert_error(locked.get("/maps"), 401, "UNAUTHORIZED")
    _declared(locked, "GET", "/maps", 401)


def test_an_unexpected_exception_answers_500_with_the_body(make_settings: Callable[..., Any],
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    with TestClient(create_app(make_settings()), raise_server_exceptions=False) as client:
        def broken() -> None:
            raise RuntimeError("a bug")

        monkeypatch.setattr(client.app.state.service.maps, "list_maps", broken)  # type: ignore[attr-defined]
        body = _assert_error(client.get("/maps"), 500, "INTERNAL_ERROR")
        assert "RuntimeError" in body["message"] and "a bug" not in body["message"]  # no internals leak
        _declared(client, "GET", "/maps", 500)


def test_the_document_declares_the_error_body_on_every_error_of_every_operation(client: TestClient) -> None:
    document = client.get("/openapi.json").json()
    assert "HTTPValidationError" not in document["components"]["schemas"]
    seen = 0
    for path, item in document["paths"].items():
        for method, operation in item.items():
            statuses = {int(s) for s in operation["responses"]}
            assert 500 in statuses, (method, path)
            if operation.get("parameters") or "requestBody" in operation:
                assert 422 in statuses, (method, path)
            for status, response in operation["responses"].items():
                if int(status) < 400 or (path, status) == ("/ready", "503"):  # /ready's 503 is its report
                    continue
                assert response["content"]["application/json"]["schema"] == {"$ref": ERROR_REF}, (method, path, status)
                seen += 1
    assert seen >= 40


def test_range_tokens_are_a_pattern_not_an_enum_with_colliding_names(client: TestClient) -> None:
    document = client.get("/openapi.json").json()
    ranges = document["components"]["schemas"]["LaserScanIn"]["properties"]["ranges"]["items"]["anyOf"]
    (token,) = [t for t in ranges if t.get("type") == "string"]
    assert "enum" not in token
    accepted = ["inf", "+inf", "-inf", "Infinity", "+Infinity", "-Infinity", "nan", "NaN"]
    assert all(re.fullmatch(token["pattern"], t) for t in accepted)
    assert not any(re.fullmatch(token["pattern"], t) for t in ["INF", "+nan", "infinity", "1.5", ""])


def test_a_client_that_goes_away_mid_body_is_not_a_server_error() -> None:
    # every such client was logged as "Exception in ASGI application" (ClientDisconnect)
    app = FastAPI()
    install_error_handlers(app)

    @app.post("/upload")
    async def upload(request: Request) -> dict[str, int]:
        return {"bytes": len(await request.body())}

    messages = [{"type": "http.request", "body": b"x" * 10, "more_body": True}, {"type": "http.disconnect"}]
    sent: list[dict[str, Any]] = []

    async def receive() -> dict[str, Any]:
        return messages.pop(0)

    async def send(message: dict[str, Any]) -> None:
        sent.append(message)

    scope = {"type": "http", "method": "POST", "path": "/upload", "headers": [], "query_string": b"",
             "http_version": "1.1", "scheme": "http", "server": ("t", 80), "client": ("c", 1), "root_path": ""}
    asyncio.run(app(scope, receive, send))  # no exception escapes to the server
    assert sent[0]["type"] == "http.response.start" and sent[0]["status"] == CLIENT_CLOSED_REQUEST, sent
