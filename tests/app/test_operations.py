"""Operations: configuration, one structured access record per request, Prometheus metrics, docs."""

from __future__ import annotations

import json
import logging
import os
import socket
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.conftest import ROOT
from app.__main__ import main as cli_main
from app.config import Settings
from app.ops.logs import JsonFormatter, KeyValueFormatter
from app.api.factory import create_app


def test_settings_come_from_fuzzyrisk_variables(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("FUZZYRISK_PORT", "9123")
    monkeypatch.setenv("FUZZYRISK_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("FUZZYRISK_SNAPSHOT_EVERY", "7")
    settings = Settings()
    assert (settings.port, settings.data_dir, settings.snapshot_every) == (9123, tmp_path, 7)
    assert Settings(_env_file=None).host == "127.0.0.1"


@pytest.mark.parametrize(("variable", "value"), [("FUZZYRISK_PORT", "0"), ("FUZZYRISK_MAX_PLAN_TIME_S", "-1"),
                                                 ("FUZZYRISK_LOG_FORMAT", "xml")])
def test_unusable_settings_are_refused(monkeypatch: pytest.MonkeyPatch, variable: str, value: str) -> None:
    monkeypatch.setenv(variable, value)
    with pytest.raises(ValueError, match=variable.removeprefix("FUZZYRISK_").lower()):
        Settings()


def test_command_line_options_override_the_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    seen: dict[str, Any] = {}

    def run(server: Any, sockets: list[socket.socket]) -> None:  # in place of uvicorn's serving loop
        seen.update(config=server.config, address=sockets[0].getsockname())
        for sock in sockets:
            sock.close()
        server.started = True

    monkeypatch.setenv("FUZZYRISK_PORT", "9999")
    monkeypatch.setenv("NUMBA_CACHE_DIR", os.environ.get("NUMBA_CACHE_DIR", ""))  # restored after the test
    monkeypatch.setattr("uvicorn.Server.run", run)
    monkeypatch.setattr("app.__main__.configure_logging", lambda **kw: seen.update(logging=kw))
    with socket.socket() as probe:
        probe.bind(("0.0.0.0", 0))
        port = probe.getsockname()[1]
    cli_main(["--port", str(port), "--data-dir", str(tmp_path), "--host", "0.0.0.0"])
    config = seen["config"]
    assert seen["address"] == ("0.0.0.0", port)  # uvicorn serves the socket bound before anything else
    assert config.app.state.settings.data_dir == tmp_path and config.app.state.settings.port == port
    assert config.access_log is False and config.timeout_graceful_shutdown > 0
    assert seen["logging"] == {"log_format": "json", "level": "INFO"}


def test_each_request_is_one_access_record(lab: TestClient, kit: Any, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="fuzzyrisk.access"):
        lab.post("/maps/lab/scans", json={"scans": [kit.laser()]})
        lab.get("/maps/nope")
    records = [r for r in caplog.records if r.name == "fuzzyrisk.access"]
    assert len(records) == 2
    first, second = (r.fields for r in records)  # type: ignore[attr-defined]
    assert (first["method"], first["path"], first["route"], first["status"]) == (
        "POST", "/maps/lab/scans", "/maps/{name}/scans", 200)
    assert first["duration_ms"] > 0 and second["status"] == 404
    line = json.loads(JsonFormatter().format(records[0]))
    assert line["msg"] == "request" and line["status"] == 200 and "ts" in line
    kv = KeyValueFormatter().format(records[0])
    assert "method=POST" in kv and "status=200" in kv and "duration_ms=" in kv


def _metric(text: str, prefix: str) -> float:
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(prefix))


def test_metrics_count_requests_scans_rays_and_fusion_time(lab: TestClient, kit: Any) -> None:
    lab.post("/maps/lab/scans", json={"scans": [kit.laser(beams=90), kit.laser(beams=10)]})
    lab.post("/maps/lab/scans", json={"scans": [{**kit.laser(), "angle_increment": 0}]})
    text = lab.get("/metrics").text
    assert _metric(text, 'fuzzyrisk_scans_fused_total{model="fuzzy"}') == 2
    assert _metric(text, 'fuzzyrisk_rays_total{model="fuzzy"}') == 100
    assert _metric(text, 'fuzzyrisk_cells_updated_total{model="fuzzy"}') > 100
    assert _metric(text, 'fuzzyrisk_fusion_duration_seconds_count{model="fuzzy"}') == 1
    assert _metric(text, 'fuzzyrisk_batches_rejected_total{reason="Invalid"}') == 1
    assert _metric(text, 'fuzzyrisk_http_requests_total{method="POST",route="/maps/{name}/scans",status="200"}') == 1
    assert _metric(text, 'fuzzyrisk_http_requests_total{method="POST",route="/maps/{name}/scans",status="422"}') == 1
    assert _metric(text, "fuzzyrisk_maps ") == 1


def test_docs_are_served_with_the_binary_upload_documented(client: TestClient) -> None:
    assert client.get("/docs").status_code == 200
    spec = client.get("/openapi.json").json()
    body = spec["paths"]["/maps/{name}/scans"]["post"]["requestBody"]["content"]
    assert {"application/json", "application/x-npy", "application/octet-stream"} <= set(body)
    assert body["application/json"]["schema"]["$ref"] == "#/components/schemas/ScanBatch"
    assert "ScanBatch" in spec["components"]["schemas"] and "LaserScanIn" in spec["components"]["schemas"]
    params = {p["name"] for p in spec["paths"]["/maps/{name}/scans"]["post"]["parameters"]}
    assert {"x", "y", "z", "theta", "qx", "qw", "angle_min", "range_max"} <= params
    assert client.get("/redoc").status_code == 200 and "/docs-assets/redoc.standalone.js" in client.get("/redoc").text
    assert client.get("/docs-assets/swagger-ui-bundle.js").status_code == 200
    assert client.get("/docs-assets/..%2Fcore.py").status_code == 404  # a fixed list of files, nothing else
    metrics = client.get("/metrics").text
    assert _metric(metrics, 'fuzzyrisk_http_requests_total{method="GET",route="/openapi.json",status="200"}') == 1


def test_every_documented_example_works_when_pasted(client: TestClient) -> None:
    """Walk the examples of /openapi.json as a user of /docs would: create, scan, query, plan, export."""
    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    lab_map, hall_map, growing_map = schemas["MapCreate"]["examples"]
    assert client.post("/maps", json=lab_map).status_code == 201
    assert client.post("/maps", json=hall_map).status_code == 201
    assert client.post("/maps", json=growing_map).json()["extent"] == "growing"
    scan_examples = spec["paths"]["/maps/{name}/scans"]["post"]["requestBody"]["content"]["application/json"]["examples"]
    assert client.post(f"/maps/{lab_map['name']}/scans", json=scan_examples["laser"]["value"]).status_code == 200
    assert client.post(f"/maps/{growing_map['name']}/scans", json=scan_examples["laser"]["value"]).status_code == 200
    assert client.post(f"/maps/{hall_map['name']}/scans", json=scan_examples["cloud"]["value"]).status_code == 200
    (query,) = schemas["RiskQuery"]["examples"]
    answer = client.post(f"/maps/{lab_map['name']}/risk/query", json=query)
    assert answer.status_code == 200 and len(answer.json()["risk"]) == len(query["points"])


def test_the_configuration_page_documents_every_setting() -> None:
    page = (ROOT / "docs" / "configuration.md").read_text()
    for name in Settings.model_fields:
        assert f"`FUZZYRISK_{name.upper()}`" in page, name


def test_behind_a_path_prefix_the_schema_names_the_prefix_as_its_server(make_settings: Any) -> None:
    with TestClient(create_app(make_settings()), root_path="/fz") as prefixed:
        spec = prefixed.get("/openapi.json").json()
        assert spec["servers"][0] == {"url": "/fz"}
        assert "/fz/openapi.json" in prefixed.get("/docs").text
        assert "servers" not in prefixed.app.openapi()  # the cached schema is not changed
