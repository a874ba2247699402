"""Property-based requests generated from the service's own OpenAPI schema (schemathesis).

Every operation gets valid and invalid inputs (schemathesis' positive and negative modes)
on a small, derandomized budget. Two thirds of the generated map names are redirected to maps
that exist (one 2-D, one 3-D), so the generated bodies reach fusion, risk and planning instead
of stopping at a 404. The properties: no answer is a 5xx, except a 503 where the operation
documents one (a busy planner); every error answer is the one error body, with a status the
operation declares.
"""

from __future__ import annotations

import re
import tempfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.generation import GenerationMode

from app.config import Settings
from app.api.factory import create_app
from bench._client import ServerProcess

from .conftest import SENT, STATUSES, assert_error_body, auth, cloud, laser

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

TARGETS = {
    "s-flat": ({"name": "s-flat", "resolution": 0.1, "origin": [-2.0, -2.0], "size": [4.0, 4.0]}, laser()),
    "s-cube": ({"name": "s-cube", "resolution": 0.2, "origin": [-2.0, -2.0, 0.0], "size": [4.0, 4.0, 2.0]}, cloud()),
}
EXAMPLES = 15  # per operation and mode: ~400 requests, well under a minute
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


@pytest.fixture(scope="session")
def fuzz_client(hostile_server: ServerProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=hostile_server.url, headers=auth(), timeout=60.0) as client:
        yield client


def _operations() -> list[Any]:
    """The service's operations, from the same OpenAPI document the live server publishes.

    (Built from ``create_app`` at collection time; schemathesis' own pytest plugin cannot be
    used: 4.32 writes ``request.node._nodeid``, which pytest 9 no longer has.)
    """
    with tempfile.TemporaryDirectory() as tmp:
        raw = create_app(Settings(data_dir=Path(tmp) / "data")).openapi()
    schema = schemathesis.openapi.from_dict(raw)
    return [result.ok() for result in schema.get_all_operations()]


def _has_input(op: Any) -> bool:
    return any(len(params) for params in (op.path_parameters, op.query, op.headers, op.body))


# (operation, mode): an operation without parameters or body has no invalid input to generate
RUNS = [(op, mode) for op in _operations() for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE)
        if mode is GenerationMode.POSITIVE or _has_input(op)]


def _ensure_targets(client: httpx.Client) -> None:
    """(Re)create the target maps, with one scan each (a generated DELETE may have removed them)."""
    present = {m["name"] for m in client.get("/maps").json()}
    for name, (body, scan) in TARGETS.items():
        if name not in present:
            client.post("/maps", json=body).raise_for_status()
            client.post(f"/maps/{name}/scans", json={"scans": [scan]}).raise_for_status()


def _aim(case: Any) -> None:
    """Send two thirds of the well-formed generated names to an existing map (deterministically)."""
    params = case.path_parameters or {}
    name = params.get("name")
    if isinstance(name, str) and NAME.fullmatch(name):
        h = zlib.crc32(name.encode())
        if h % 3:
            params["name"] = list(TARGETS)[h % len(TARGETS)]


def _documented(case: Any, status: int) -> bool:
    responses = case.operation.definition.raw.get("responses", {})
    return str(status) in responses


def _declared_body(case: Any, status: int) -> str | None:
    """The component the operation declares for that status's JSON body (``ErrorBody`` for errors), if any."""
    response = case.operation.definition.raw.get("responses", {}).get(str(status), {})
    ref = response.get("content", {}).get("application/json", {}).get("schema", {}).get("$ref", "")
    return ref.rsplit("/", 1)[-1] or None


@pytest.mark.parametrize(("operation", "mode"), RUNS, ids=[f"{op.label}-{mode.value}" for op, mode in RUNS])
def test_no_generated_request_gets_a_server_error(operation: Any, mode: GenerationMode,
                                                  hostile_server: ServerProcess, fuzz_client: httpx.Client) -> None:
    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    def check(case: Any) -> None:
        _ensure_targets(fuzz_client)
        _aim(case)
        response = case.call(base_url=hostile_server.url, headers=auth(), timeout=60)
        SENT[f"schemathesis-{mode.value}"] += 1
        status = response.status_code
        STATUSES[status] += 1
        assert status < 500 or (status == 503 and _documented(case, 503)), (
            f"{case.method} {case.formatted_path} -> {status}: {response.text[:300]}"
        )
        if status >= 400:
            assert _documented(case, status), f"{case.method} {case.formatted_path} -> {status} is not declared: {response.text[:300]}"
            # the one error body, except where the operation declares its own for that status (GET /ready's 503
            # is its Readiness, while the kernels compile)
            declared = _declared_body(case, status)
            if declared in (None, "ErrorBody"):
                assert_error_body(response)
            else:
                assert set(response.json()) <= set(
                    case.operation.schema.raw_schema["components"]["schemas"][declared]["properties"]), response.text[:300]

    check()
