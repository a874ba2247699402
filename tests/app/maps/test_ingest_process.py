"""Large JSON batches are parsed in a process of their own: the same maps and the same errors as in
the server's threads, and the process ends with the service or is replaced when it dies."""

from __future__ import annotations

import json
import os
import signal
import time
from typing import Any

import numpy as np
import psutil
from fastapi.testclient import TestClient

from app.maps.ingest_process import PROCESS_PARSE_BYTES
from tests.conftest import error_message


def _big_batch(kit: Any, scans: int = 60, beams: int = 720) -> dict[str, Any]:
    batch = {"scans": [kit.laser(x=0.01 * i, beams=beams) for i in range(scans)]}
    assert len(json.dumps(batch)) > PROCESS_PARSE_BYTES
    return batch


def _parse_processes(client: TestClient) -> list[psutil.Process]:
    executor = client.app.state.service.writes.parse_process._executor  # type: ignore[attr-defined]
    return [psutil.Process(p.pid) for p in getattr(executor, "_processes", {}).values()] if executor else []


def test_a_large_json_batch_makes_the_same_map_as_the_same_scans_sent_in_small_batches(make_client: Any,
                                                                                       kit: Any) -> None:
    client = make_client()
    batch = _big_batch(kit)
    for name in ("whole", "parts"):
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    whole = client.post("/maps/whole/scans", content=json.dumps(batch), headers={"Content-Type": "application/json"})
    assert whole.status_code == 200, whole.text
    assert len(_parse_processes(client)) == 1  # it went through the process
    for scan in batch["scans"]:  # one scan a batch: small bodies, parsed on the event loop
        assert client.post("/maps/parts/scans", json={"scans": [scan]}).status_code == 200
    # a batch fuses its scans one after another, as separate batches do
    np.testing.assert_array_equal(kit.risk_npy(client, "whole"), kit.risk_npy(client, "parts"))


def test_a_large_json_batch_keeps_its_stamps_through_the_process(make_client: Any, kit: Any) -> None:
    client = make_client()
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    batch = _big_batch(kit)
    for i, scan in enumerate(batch["scans"][::2]):  # every other scan stamped by the robot, the rest on arrival
        scan["header"] = {"stamp": {"sec": 1_700_000_000 + i, "nanosec": 7}}
    before = time.time_ns()
    assert client.post("/maps/lab/scans", content=json.dumps(batch),
                       headers={"Content-Type": "application/json"}).status_code == 200
    after = time.time_ns()
    assert len(_parse_processes(client)) == 1  # it went through the process
    stamps = [p["header"]["stamp"]["sec"] * 10**9 + p["header"]["stamp"]["nanosec"]
              for p in client.get("/maps/lab/trajectory").json()["poses"]]
    assert stamps[::2] == [(1_700_000_000 + i) * 10**9 + 7 for i in range(len(stamps[::2]))]
    assert len(set(stamps[1::2])) == 1 and before <= stamps[1] <= after


def test_a_large_json_batch_gets_the_same_errors_from_the_process(make_client: Any, kit: Any) -> None:
    client = make_client(max_batch_cells=10_000)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    headers = {"Content-Type": "application/json"}
    batch = _big_batch(kit)
    batch["scans"][7]["ranges"][3] = "three"
    bad = client.post("/maps/lab/scans", content=json.dumps(batch), headers=headers)
    assert bad.status_code == 422
    assert any(d["loc"][:3] == ["body", "scans", 7] for d in bad.json()["details"]), bad.json()
    too_much = client.post("/maps/lab/scans", content=json.dumps(_big_batch(kit)), headers=headers)
    assert too_much.status_code == 413 and "FUZZYRISK_MAX_BATCH_CELLS" in error_message(too_much)
    assert len(_parse_processes(client)) == 1
    assert kit.version(client, "lab") == 0


def _until_gone(process: psutil.Process) -> None:
    """Wait until the process has ended (gone, or a zombie its parent has not reaped yet): on its condition, with a
    net against a hang far beyond what a busy machine takes."""
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        try:
            if not process.is_running() or process.status() == psutil.STATUS_ZOMBIE:
                return
        except psutil.NoSuchProcess:
            return
        time.sleep(0.05)
    raise AssertionError(f"process {process.pid} still runs")


def test_a_dead_parse_process_is_replaced_and_the_last_ends_with_the_service(make_client: Any, kit: Any) -> None:
    client = make_client()
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    body, headers = json.dumps(_big_batch(kit)), {"Content-Type": "application/json"}
    assert client.post("/maps/lab/scans", content=body, headers=headers).status_code == 200
    (first,) = _parse_processes(client)
    os.kill(first.pid, signal.SIGKILL)  # while idle: the next batch finds it dead and a new one parses it
    _until_gone(first)
    assert client.post("/maps/lab/scans", content=body, headers=headers).status_code == 200
    (second,) = _parse_processes(client)
    assert second.pid != first.pid and kit.version(client, "lab") == 2
    client.__exit__(None, None, None)
    late = client.app.state.service.writes.parse_process  # type: ignore[attr-defined]
    assert late._executor is None and late._closed  # a batch arriving now would start none
    _until_gone(second)
