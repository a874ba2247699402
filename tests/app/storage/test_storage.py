"""Durable storage: maps survive restarts bit for bit, snapshots plus replay, deletes, refused batches."""

from __future__ import annotations

import json
import shutil
import socket
import sqlite3
import statistics
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import numpy as np
import psycopg
import pytest
from fastapi.testclient import TestClient

from app.storage.committer import GroupCommitter
from app.config import Settings
from app.errors import error_body_of
from app.api.factory import create_app
from app.ops.metrics import Metrics
from app.storage import (
    BatchRecord,
    CommitUncertain,
    MapGone,
    MapHead,
    NameTaken,
    SqliteStorage,
    Storage,
    StorageUnavailable,
    StoredMap,
)
from app.storage.postgres import PostgresStorage
from fuzzyocc import FuzzyMap, GridSpec, LaserScan, cast_work
from tests.conftest import error_message


def _rows(where: Path | Settings, table: str) -> list[tuple[Any, ...]]:
    """(map, version) of the rows of ``table`` in a data directory's SQLite, or in the settings' store."""
    column = "seq" if table == "batches" else "version"
    # a discarded batch stays as an empty tombstone (its version stays taken): not a batch
    sql = f"SELECT map, {column} FROM {table} WHERE length(payload) > 0 ORDER BY map, {column}"
    if isinstance(where, Settings) and where.database_url is not None:  # (PostgreSQL keeps every payload in its row)
        with psycopg.connect(where.database_url.get_secret_value()) as db:
            return [tuple(row) for row in db.execute(sql).fetchall()]
    data_dir = where.data_dir if isinstance(where, Settings) else where
    with sqlite3.connect(data_dir / "fuzzyrisk.sqlite3") as db:  # a big payload is a file the row names
        return db.execute(sql.replace("length(payload) > 0", "(length(payload) > 0 OR file IS NOT NULL)")).fetchall()


@pytest.fixture(params=["sqlite", "postgres"])
def on(request: pytest.FixtureRequest) -> dict[str, Any]:
    """Settings of a service on each store: SQLite in its data directory, then a new PostgreSQL database."""
    if request.param == "sqlite":
        return {}
    return {"database_url": request.getfixturevalue("postgres_server").create_database()}


def _scans(kit: Any, n: int) -> list[dict[str, Any]]:
    return [{"scans": [kit.laser(x=0.1 * k, y=-0.2 * k, theta=0.3 * k, wall=2.05 + 0.1 * k)]} for k in range(n)]


@pytest.mark.parametrize("model", ["fuzzy", "bayes"])
def test_a_restart_serves_the_same_maps_bit_for_bit(make_client: Any, kit: Any, model: str,
                                                    on: dict[str, Any]) -> None:
    first = make_client(**on)
    first.post("/maps", json={**kit.MAP_2D, "model": model})
    for body in _scans(kit, 5):
        assert first.post("/maps/lab/scans", json=body).status_code == 200
    info, risk = first.get("/maps/lab").json(), kit.risk_npy(first, "lab")
    first.__exit__(None, None, None)

    second = make_client(**on)
    assert second.get("/maps/lab").json() == info
    assert kit.risk_npy(second, "lab").tobytes() == risk.tobytes()


def test_snapshots_keep_the_batches_they_cover_and_a_restart_replays_the_rest(make_client: Any, make_settings: Any,
                                                                              kit: Any) -> None:
    client = make_client(snapshot_every=3)
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    bytes_before = client.get("/maps/lab").json()["history"]["bytes"]
    for body in _scans(kit, 7):
        client.post("/maps/lab/scans", json=body)
    kit.snapshots_stored(client)
    assert _rows(data_dir, "snapshots") == [("lab", 6)]
    assert _rows(data_dir, "batches") == [("lab", v) for v in range(1, 8)]  # the history, under its budget
    history = client.get("/maps/lab").json()["history"]
    assert history["from_version"] == 0 and history["scans"] == 7 and history["bytes"] > bytes_before == 0
    risk = kit.risk_npy(client, "lab")

    # a crash image: the files as they are on disk now, while the service still runs
    crashed = data_dir.parent / "crashed"
    shutil.copytree(data_dir, crashed)
    replayed = TestClient(create_app(Settings(data_dir=crashed, plan_warmup=False)))
    with replayed:
        assert replayed.get("/maps/lab").json()["version"] == 7
        assert kit.risk_npy(replayed, "lab").tobytes() == risk.tobytes()
        entry = replayed.app.state.service.maps.entry("lab")  # type: ignore[attr-defined]
        assert [version for version, _, _ in entry.log] == [7]  # the snapshot, then only the batch after it
        assert replayed.get("/maps/lab").json()["history"] == history


def _hold_snapshot_writes(monkeypatch: pytest.MonkeyPatch) -> tuple[threading.Event, threading.Event]:
    """Snapshot writes wait for the second event (the first is set when one starts)."""
    original, writing, release = SqliteStorage.write_snapshot, threading.Event(), threading.Event()

    def held(self: SqliteStorage, *args: Any) -> None:
        writing.set()
        assert release.wait(10)
        original(self, *args)

    monkeypatch.setattr(SqliteStorage, "write_snapshot", held)
    return writing, release


def test_a_batch_is_acknowledged_before_its_snapshot_is_written_and_a_delete_waits_for_it(
        make_client: Any, make_settings: Any, kit: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    # the batch that made a snapshot due waited for its deflate and fsync (one scan in every 200 was
    # an innocent client's slowest in bench abuse)
    writing, release = _hold_snapshot_writes(monkeypatch)
    client = make_client(snapshot_every=2)
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    bodies = _scans(kit, 3)
    for body in bodies[:2]:
        assert client.post("/maps/lab/scans", json=body).status_code == 200
    assert writing.wait(10) and _rows(data_dir, "snapshots") == []  # acknowledged, its snapshot still being written
    assert client.post("/maps/lab/scans", json=bodies[2]).json()["version"] == 3  # the map goes on meanwhile
    with ThreadPoolExecutor(1) as pool:
        deleting = pool.submit(client.delete, "/maps/lab")
        time.sleep(0.2)
        assert not deleting.done()  # a delete waits: the snapshot must not land after the rows are gone
        release.set()
        assert deleting.result().status_code == 204
    assert _rows(data_dir, "snapshots") == [] and _rows(data_dir, "batches") == []


def test_a_snapshot_is_of_the_version_that_made_it_due(make_client: Any, make_settings: Any, kit: Any,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    _, release = _hold_snapshot_writes(monkeypatch)
    client = make_client(snapshot_every=2)
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    for body in _scans(kit, 3):  # 3 is fused while the snapshot of 2 waits to be written
        assert client.post("/maps/lab/scans", json=body).status_code == 200
    risk = kit.risk_npy(client, "lab")
    release.set()
    kit.snapshots_stored(client)
    assert _rows(data_dir, "snapshots") == [("lab", 2)] and _rows(data_dir, "batches") == [("lab", 1), ("lab", 2),
                                                                                          ("lab", 3)]
    client.__exit__(None, None, None)
    assert kit.risk_npy(make_client(), "lab").tobytes() == risk.tobytes()


def test_a_crash_image_without_snapshot_replays_every_batch(make_client: Any, make_settings: Any, kit: Any) -> None:
    client = make_client()
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    for body in _scans(kit, 4):
        client.post("/maps/lab/scans", json=body)
    assert _rows(data_dir, "snapshots") == [] and len(_rows(data_dir, "batches")) == 4
    crashed = data_dir.parent / "crashed"
    shutil.copytree(data_dir, crashed)
    with TestClient(create_app(Settings(data_dir=crashed, plan_warmup=False))) as replayed:
        assert replayed.get("/maps/lab").json()["scans_fused"] == 4
        assert kit.risk_npy(replayed, "lab").tobytes() == kit.risk_npy(client, "lab").tobytes()
        assert replayed.get("/maps/lab/scans/last").json()["version"] == 4


@pytest.mark.parametrize("max_history_bytes", [2**30, 0])
def test_a_graceful_stop_snapshots_every_map(make_client: Any, make_settings: Any, kit: Any,
                                            on: dict[str, Any], max_history_bytes: int) -> None:
    client = make_client(max_history_bytes=max_history_bytes, **on)
    settings = make_settings(**on)
    client.post("/maps", json=kit.MAP_2D)
    for body in _scans(kit, 2):
        client.post("/maps/lab/scans", json=body)
    client.__exit__(None, None, None)
    if max_history_bytes:  # the history stays
        assert _rows(settings, "snapshots") == [("lab", 2)] and _rows(settings, "batches") == [("lab", 1), ("lab", 2)]
    else:  # no history beyond what a restart needs: the snapshot is the base, the batches it covers are gone
        assert _rows(settings, "bases") == [("lab", 2)] and _rows(settings, "snapshots") == []
        assert _rows(settings, "batches") == []


def test_deleting_a_map_removes_its_rows_for_good(make_client: Any, make_settings: Any, kit: Any,
                                                  on: dict[str, Any]) -> None:
    client = make_client(snapshot_every=2, **on)
    data_dir = make_settings(**on)
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps", json={**kit.MAP_2D, "name": "kept"})
    for body in _scans(kit, 3):
        client.post("/maps/lab/scans", json=body)
    assert client.delete("/maps/lab").status_code == 204
    assert _rows(data_dir, "batches") == [] and _rows(data_dir, "snapshots") == []
    client.__exit__(None, None, None)
    again = make_client(**on)
    assert [m["name"] for m in again.get("/maps").json()] == ["kept"]
    assert again.post("/maps", json=kit.MAP_2D).json()["version"] == 0  # the name is free, the map new


def test_a_refused_batch_leaves_nothing_on_disk(make_client: Any, make_settings: Any, kit: Any,
                                               on: dict[str, Any]) -> None:
    lab = make_client(**on)
    assert lab.post("/maps", json=kit.MAP_2D).status_code == 201
    assert lab.post("/maps/lab/scans", json={"scans": [kit.laser(), {**kit.laser(), "angle_increment": 0}]}
                    ).status_code == 422
    assert _rows(make_settings(**on), "batches") == []


def test_a_batch_that_fails_while_applied_is_not_kept(make_settings: Any, kit: Any,
                                                      monkeypatch: pytest.MonkeyPatch, on: dict[str, Any]) -> None:
    settings = make_settings(**on)
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        client.post("/maps", json=kit.MAP_2D)
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 200

        def broken(self: FuzzyMap, scans: Any, prepared: Any = None) -> Any:
            raise MemoryError("simulated")

        monkeypatch.setattr(FuzzyMap, "integrate_batch", broken)
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 500
        assert _rows(settings, "batches") == [("lab", 1)]
        assert client.get("/maps/lab").json()["version"] == 1
        monkeypatch.undo()
        # version 2 stays taken (services.py: a failed batch's version is never reused), so the map skips it
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).json()["version"] == 3


def test_the_map_a_failed_batch_replaced_is_freed_at_once(make_settings: Any, kit: Any,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    # the traceback's frames held the replaced map (a cycle with the error): after a MemoryError, that map
    # stayed in memory until the cyclic collector ran
    import gc
    import weakref

    with TestClient(create_app(make_settings()), raise_server_exceptions=False) as client:
        client.post("/maps", json=kit.MAP_2D)
        replaced = weakref.ref(client.app.state.service.maps.entry("lab").map)  # type: ignore[attr-defined]

        def broken(self: FuzzyMap, scans: Any, prepared: Any = None) -> Any:
            raise MemoryError("simulated")

        monkeypatch.setattr(FuzzyMap, "integrate_batch", broken)
        gc.collect()
        gc.disable()
        try:
            assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 500
            assert client.app.state.service.maps.entry("lab").map is not replaced()  # type: ignore[attr-defined]
            assert replaced() is None
        finally:
            gc.enable()


def test_a_batch_that_fails_half_way_leaves_the_live_map_as_a_restart_rebuilds_it(
        make_settings: Any, kit: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    # a MemoryError after part of a batch was fused left the live map changed in part
    settings = make_settings()
    original = FuzzyMap.integrate_batch
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        client.post("/maps", json=kit.MAP_2D)
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 200
        before = client.get("/maps/lab/risk", params={"format": "npy"}).content

        failed: list[bool] = []

        def half(self: FuzzyMap, scans: Any, prepared: Any = None) -> Any:
            if self.spec.shape == (100, 100) and not failed:  # the test's map, once (the rebuild replays)
                failed.append(True)
                original(self, list(scans)[:1])  # the first scan changes the map...
                raise MemoryError("simulated")  # ...then the batch fails
            return original(self, scans, prepared)

        monkeypatch.setattr(FuzzyMap, "integrate_batch", half)
        two = {"scans": [kit.laser(x=1.0, wall=2.0), kit.laser(x=-1.0, wall=2.5)]}
        assert client.post("/maps/lab/scans", json=two).status_code == 500
        monkeypatch.undo()
        assert client.get("/maps/lab").json()["version"] == 1
        live = client.get("/maps/lab/risk", params={"format": "npy"}).content
        assert live == before
    with TestClient(create_app(settings)) as restarted:
        assert restarted.get("/maps/lab/risk", params={"format": "npy"}).content == live


def _keep_the_log_at_shutdown(monkeypatch: pytest.MonkeyPatch) -> None:
    """Snapshots fail only at shutdown (a full disk then, say): the batches after the last snapshot stay in the log."""
    original = SqliteStorage.write_snapshot

    def write_snapshot(self: SqliteStorage, name: str, version: int, payload: bytes,
                       incarnation: str | None = None) -> None:
        if version % 2:  # the service's own every-2 snapshots (snapshot_every=2) pass
            raise StorageUnavailable("database or disk is full")
        original(self, name, version, payload, incarnation)

    monkeypatch.setattr(SqliteStorage, "write_snapshot", write_snapshot)


def _flip_a_bit(data_dir: Path, table: str, key: str, name: str) -> None:
    with sqlite3.connect(data_dir / "fuzzyrisk.sqlite3") as db:
        (payload,) = db.execute(f"SELECT payload FROM {table} WHERE map = ? ORDER BY {key} DESC LIMIT 1",
                                (name,)).fetchone()
        damaged = bytearray(payload)
        damaged[len(damaged) // 2] ^= 0x04
        db.execute(f"UPDATE {table} SET payload = ? WHERE map = ? AND {key} = "
                   f"(SELECT {key} FROM {table} WHERE map = ? ORDER BY {key} DESC LIMIT 1)", (bytes(damaged), name, name))


@pytest.mark.parametrize(("table", "key", "what"), [("batches", "seq", "batch 3"), ("snapshots", "version", "snapshot")])
def test_a_damaged_row_quarantines_its_map_and_the_others_start(make_settings: Any, kit: Any, table: str,
                                                                 key: str, what: str,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # a flipped bit in a stored batch was fused as if nothing happened; a damaged snapshot
    # stopped the whole service
    settings = make_settings(snapshot_every=2)
    _keep_the_log_at_shutdown(monkeypatch)
    with TestClient(create_app(settings)) as client:
        for name in ("lab", "other"):
            client.post("/maps", json={**kit.MAP_2D, "name": name})
            for body in _scans(kit, 3):  # a snapshot at version 2, batch 3 after it
                assert client.post(f"/maps/{name}/scans", json=body).status_code == 200
        other = client.get("/maps/other/risk", params={"format": "npy"}).content
    monkeypatch.undo()
    _flip_a_bit(settings.data_dir, table, key, "lab")
    with TestClient(create_app(settings)) as client:
        damaged = client.get("/maps/lab")
        assert damaged.status_code == 503
        assert "quarantined" in error_message(damaged) and "checksum" in error_message(damaged)
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 503  # nothing is added to it
        assert client.get("/ready").json()["maps_quarantined"] == ["lab"]
        assert client.get("/maps/other/risk", params={"format": "npy"}).content == other
        assert client.delete("/maps/lab").status_code == 204  # dropped with its rows
        assert client.get("/maps/lab").status_code == 404
        assert client.post("/maps", json=kit.MAP_2D).status_code == 201  # the name is free again
    assert what  # the parameter names the damaged row in the test id


def test_a_database_from_before_the_checksums_still_loads(make_settings: Any, kit: Any,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    settings = make_settings()
    _keep_the_log_at_shutdown(monkeypatch)
    with TestClient(create_app(settings)) as client:
        client.post("/maps", json=kit.MAP_2D)
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 200
        risk = client.get("/maps/lab/risk", params={"format": "npy"}).content
    with sqlite3.connect(settings.data_dir / "fuzzyrisk.sqlite3") as db:
        db.execute("ALTER TABLE batches DROP COLUMN crc")  # the old schema
    with TestClient(create_app(settings)) as client:
        assert client.get("/maps/lab/risk", params={"format": "npy"}).content == risk
        assert client.post("/maps/lab/scans", json=_scans(kit, 2)[1]).status_code == 200
        assert _rows(settings.data_dir, "batches") == [("lab", 1), ("lab", 2)]
        with sqlite3.connect(settings.data_dir / "fuzzyrisk.sqlite3") as db:  # the old row unchecked, the new one summed
            assert [crc is None for (crc,) in db.execute("SELECT crc FROM batches ORDER BY seq")] == [True, False]


def test_map_metadata_survives_a_restart(make_client: Any, kit: Any, on: dict[str, Any]) -> None:
    first = make_client(**on)
    created = first.post("/maps", json={**kit.MAP_3D, "model": "bayes",
                                         "sensor": {"range_sigma": 0.07, "registration_sigma": 0.02,
                                                    "range_sigma_per_m": 0.01}}).json()
    first.__exit__(None, None, None)
    assert make_client(**on).get("/maps/hall").json() == created


def test_replayed_risk_equals_a_fresh_in_process_fusion(make_client: Any, kit: Any) -> None:
    """The service adds nothing of its own: its map is fuzzyocc's map fed the same scans."""
    from fuzzyocc import GridSpec, LaserScan, SensorModel

    client = make_client()
    client.post("/maps", json=kit.MAP_2D)
    bodies = _scans(kit, 3)
    for body in bodies:
        client.post("/maps/lab/scans", json=body)
    reference = FuzzyMap(GridSpec(origin=(-5.0, -5.0), size=(10.0, 10.0), resolution=0.1),
                         SensorModel(range_sigma=0.03, registration_sigma=0.0))
    for body in bodies:
        s = body["scans"][0]
        reference.integrate_batch([LaserScan(pose=(s["pose"]["x"], s["pose"]["y"], s["pose"]["theta"]),
                                             angle_min=s["angle_min"], angle_increment=s["angle_increment"],
                                             ranges=np.array(s["ranges"], dtype=float), range_min=s["range_min"],
                                             range_max=s["range_max"])])
    assert kit.risk_npy(client, "lab").tobytes() == reference.risk().tobytes()


def test_a_backup_taken_while_the_service_runs_serves_the_same_maps(make_settings: Any, kit: Any,
                                                                    tmp_path: Path) -> None:
    from app.cli.backup import main as backup_main

    settings = make_settings()
    copy = tmp_path / "copy" / "fuzzyrisk.sqlite3"
    copy.parent.mkdir()
    with TestClient(create_app(settings)) as client:
        client.post("/maps", json=kit.MAP_2D)
        for body in _scans(kit, 3):
            assert client.post("/maps/lab/scans", json=body).status_code == 200
        assert (settings.data_dir / "fuzzyrisk.sqlite3-wal").stat().st_size > 0  # batches still in the log
        risk = client.get("/maps/lab/risk", params={"format": "npy"}).content
        assert backup_main([str(copy), "--data-dir", str(settings.data_dir)]) == 0
        assert backup_main([str(copy), "--data-dir", str(settings.data_dir)]) == 1  # never overwrites
        assert client.post("/maps/lab/scans", json=_scans(kit, 4)[3]).status_code == 200  # still serving
    with TestClient(create_app(make_settings(data_dir=copy.parent))) as restored:
        assert restored.get("/maps/lab").json()["version"] == 3
        assert restored.get("/maps/lab/risk", params={"format": "npy"}).content == risk


def test_a_start_holds_one_map_at_a_time(make_client: Any, make_settings: Any, kit: Any) -> None:
    # a start read every batch of every map at once (377 MB of log peaked at 1.1 GB); now
    # maps load one at a time, so the peak follows the largest map, not their sum
    import asyncio
    import tracemalloc

    from app.maps import logcodec
    from app.scans import Limits, from_json
    from app.ops.metrics import Metrics
    from app.schemas import ScanBatch
    from app.service.mapservice import MapService
    from app.storage import BatchRecord, SqliteStorage

    names = [f"m{k}" for k in range(8)]
    client = make_client()
    for name in names:
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    client.__exit__(None, None, None)
    settings = make_settings()
    limits = Limits(max_scans=256, max_rays=settings.max_rays_per_scan)
    # many small batches: the log's bytes, not one batch's fusion scratch, make the peak
    payload = logcodec.encode(from_json(ScanBatch.model_validate({"scans": [kit.laser(beams=20_000)]}), 2,
                                               limits))
    per_map = 50
    storage = SqliteStorage(settings.database_path)
    heads = {head.name: head for head in storage.map_heads()}
    storage.append_batches([BatchRecord(name, heads[name].incarnation, payload, "2026-12-02T00:00:00+00:00", 1)
                            for name in names for _ in range(per_map)])
    storage.close()
    total = len(payload) * per_map * len(names)

    async def start() -> tuple[int, int]:
        service = MapService(settings, SqliteStorage(settings.database_path), Metrics())
        tracemalloc.start()
        try:
            await service.start()
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        versions = sum([(await service.reads.map_info(name)).version for name in names])
        await service.stop()
        return peak, versions

    peak, versions = asyncio.run(start())
    assert versions == per_map * len(names)  # every batch replayed
    print(f"start peak {peak / 1e6:.1f} MB for {total / 1e6:.1f} MB of log")
    assert peak < total / 2, (peak, total)


def test_a_map_is_snapshotted_once_its_log_holds_the_byte_limit(make_client: Any, make_settings: Any,
                                                                kit: Any) -> None:
    # the log of one map was bounded by a count of batches only (200 x 64 MiB = 12.5 GiB)
    client = make_client(snapshot_every=1000, snapshot_log_bytes=20_000)
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    big = [{"scans": [kit.laser(beams=1_000, wall=2.0 + 0.1 * k)]} for k in range(6)]  # about 8 kB logged each
    for k, body in enumerate(big, start=1):
        assert client.post("/maps/lab/scans", json=body).status_code == 200
        kit.snapshots_stored(client)
        snapshots = _rows(data_dir, "snapshots")
        if snapshots:
            break
    assert snapshots == [("lab", k)] and 2 <= k <= 4  # the batch that crossed 20,000 bytes of log
    assert _rows(data_dir, "batches") == [("lab", v) for v in range(1, k + 1)]  # kept: the history
    risk = kit.risk_npy(client, "lab")
    client.__exit__(None, None, None)
    assert kit.risk_npy(make_client(), "lab").tobytes() == risk.tobytes()


@pytest.mark.parametrize(("snapshot_every", "delete", "message"), [
    (2, "DELETE FROM snapshots WHERE map = 'lab'", "its snapshot (version 2) is missing"),
    (2, "DELETE FROM batches WHERE map = 'lab' AND seq = 3", "its batches up to version 3 are missing"),
    (1000, "DELETE FROM batches WHERE map = 'lab' AND seq = 2", "its batches 2 to 2 are missing"),
])
def test_rows_deleted_behind_the_services_back_quarantine_the_map(make_settings: Any, kit: Any, snapshot_every: int,
                                                                  delete: str, message: str,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    # a deleted snapshot row left a map without batches 1-2 reporting version 3; a gap inside the
    # log was replayed over
    settings = make_settings(snapshot_every=snapshot_every)
    _keep_the_log_at_shutdown(monkeypatch)
    with TestClient(create_app(settings)) as client:
        client.post("/maps", json=kit.MAP_2D)
        for body in _scans(kit, 3):  # every 2: a snapshot at version 2, batch 3 after it; every 1000: 3 batches
            assert client.post("/maps/lab/scans", json=body).status_code == 200
    monkeypatch.undo()
    with sqlite3.connect(settings.data_dir / "fuzzyrisk.sqlite3") as db:
        db.execute(delete)
    with TestClient(create_app(settings)) as client:
        damaged = client.get("/maps/lab")
        assert damaged.status_code == 503 and message in error_message(damaged)
        assert client.get("/ready").json()["maps_quarantined"] == ["lab"]



# --- the store itself, SQLite and PostgreSQL alike (replicas of the service on one PostgreSQL) ---


class Backend:
    """One fresh database of a kind: ``open()`` a store on it (closed at the end), ``sql()`` behind its back."""

    def __init__(self, kind: str, tmp_path: Path, request: pytest.FixtureRequest) -> None:
        self.kind = kind
        self.stores: list[Storage] = []
        if kind == "postgres":
            self.url = request.getfixturevalue("postgres_server").create_database()
        else:
            self.path = tmp_path / "db.sqlite3"

    def open(self) -> Storage:
        store: Storage = PostgresStorage(self.url) if self.kind == "postgres" else SqliteStorage(self.path)
        self.stores.append(store)
        return store

    def sql(self, statement: str, args: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        """Run one statement on the database directly (``?`` placeholders), as an operator would."""
        if self.kind == "postgres":
            with psycopg.connect(self.url, autocommit=True) as conn:
                cursor = conn.execute(statement.replace("?", "%s"), args)
                return [tuple(row) for row in cursor.fetchall()] if cursor.description else []
        with sqlite3.connect(self.path) as db:
            return db.execute(statement, args).fetchall()


@pytest.fixture(params=["sqlite", "postgres"])
def backend(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Backend]:
    made = Backend(request.param, tmp_path, request)
    yield made
    for store in made.stores:
        store.close()


@pytest.fixture
def postgres(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Backend]:
    """A fresh PostgreSQL database, for what only PostgreSQL has (connections, replicas opening it at once)."""
    made = Backend("postgres", tmp_path, request)
    yield made
    for store in made.stores:
        store.close()


@pytest.fixture
def store(backend: Backend) -> Storage:
    """A fresh store: SQLite in a new file, or PostgreSQL on a new database."""
    return backend.open()


def _make(store: Storage, name: str = "m", incarnation: str | None = "i1") -> None:
    store.create_map(name, {"name": name, "incarnation": incarnation}, "t0")


def _append(store: Storage, payload: bytes, name: str = "m", incarnation: str | None = "i1", scans: int = 1) -> int:
    (version,) = store.append_batches([BatchRecord(name, incarnation, payload, "t1", scans)])
    return version


def _versions(stored: StoredMap | None) -> list[int]:
    assert stored is not None
    return [version for version, _ in stored.batches]


def test_the_store_gives_each_batch_its_maps_next_version_in_the_callers_order(store: Storage) -> None:
    _make(store, "m")
    _make(store, "a", incarnation=None)
    records = [BatchRecord("m", "i1", b"m1", "t1", 2), BatchRecord("a", None, b"a1", "t2", 1),
               BatchRecord("m", "i1", b"m2", "t3", 3), BatchRecord("a", None, b"a2", "t4", 4)]
    assert store.append_batches(records) == [1, 1, 2, 2]
    assert store.append_batches([BatchRecord("a", None, b"a3", "t5", 1)]) == [3]
    m, a = store.load_map("m"), store.load_map("a")
    assert m is not None and m.batches == [(1, b"m1"), (2, b"m2")] and m.version == 2 and m.incarnation == "i1"
    assert a is not None and a.batches == [(1, b"a1"), (2, b"a2"), (3, b"a3")] and a.updated == "t5"
    assert store.map_head("m") == MapHead("m", {"name": "m", "incarnation": "i1"}, "t3", 2, 0, 5, "i1", 0, 4, 5)
    assert store.append_batches([]) == []


def test_appends_from_many_threads_and_two_stores_get_gapless_versions(backend: Backend) -> None:
    # two replicas (PostgreSQL) x 4 threads x 50 batches to one map: the map's row orders them
    stores = [backend.open() for _ in range(2 if backend.kind == "postgres" else 1)]
    _make(stores[0])
    per_thread, threads = 50, 4
    got: dict[bytes, int] = {}
    lock = threading.Lock()

    def writer(store: Storage, tag: str) -> None:
        mine = []
        for k in range(per_thread):
            payload = f"{tag}-{k}".encode()
            version = _append(store, payload)
            mine.append(version)
            with lock:
                got[payload] = version
        assert mine == sorted(mine)  # one writer's batches keep their order

    with ThreadPoolExecutor(threads * len(stores)) as pool:
        futures = [pool.submit(writer, store, f"{s}/{t}") for s, store in enumerate(stores) for t in range(threads)]
        for future in futures:
            future.result(timeout=120)
    total = per_thread * threads * len(stores)
    assert sorted(got.values()) == list(range(1, total + 1))  # each version exactly once
    stored = stores[-1].load_map("m")
    assert stored is not None and stored.damage == [] and stored.version == total
    assert {payload: version for version, payload in stored.batches} == got  # the rows are the answers
    head = stores[0].map_head("m")
    assert head is not None and head.version == total and head.scans == total


def test_groups_of_the_same_maps_in_opposite_orders_do_not_deadlock(backend: Backend) -> None:
    # two replicas committing [a, b] and [b, a] at once: the rows are locked in name order, never crosswise
    stores = [backend.open() for _ in range(2 if backend.kind == "postgres" else 1)]
    for name in ("a", "b"):
        _make(stores[0], name)
    rounds = 60

    def writer(store: Storage, names: list[str]) -> list[list[int]]:
        return [store.append_batches([BatchRecord(n, "i1", n.encode(), "t1", 1) for n in names])
                for _ in range(rounds)]

    with ThreadPoolExecutor(2) as pool:
        forward = pool.submit(writer, stores[0], ["a", "b", "a"])
        backward = pool.submit(writer, stores[-1], ["b", "a", "b"])
        results = forward.result(timeout=120) + backward.result(timeout=120)
    for versions in results:  # each map's own records in their order: a map's later record, a later version
        assert versions[2] > versions[0]
    assert [stores[0].map_head(n).version for n in ("a", "b")] == [3 * rounds, 3 * rounds]  # type: ignore[union-attr]


@pytest.mark.parametrize("gone", ["deleted", "created again"])
def test_a_batch_for_a_map_that_is_gone_fails_its_whole_group(store: Storage, gone: str) -> None:
    _make(store, "m")
    _make(store, "other")
    assert _append(store, b"m1") == 1
    store.delete_map("m")
    if gone == "created again":
        _make(store, "m", incarnation="i2")
    with pytest.raises(MapGone, match="m"):
        store.append_batches([BatchRecord("other", "i1", b"o1", "t2", 1), BatchRecord("m", "i1", b"m2", "t2", 1)])
    other = store.load_map("other")
    assert other is not None and other.batches == [] and other.version == 0  # nothing of the group stored
    assert store.map_head("other").updated == "t0"  # type: ignore[union-attr]
    if gone == "created again":
        assert store.load_map("m").batches == []  # type: ignore[union-attr]
        assert _append(store, b"new", incarnation="i2") == 1
    else:
        assert store.load_map("m") is None
    assert _append(store, b"o1", name="other") == 1  # the refused group took no version


def test_a_map_of_no_incarnation_takes_batches_for_none(store: Storage) -> None:
    store.create_map("old", {"name": "old"}, "t0")  # a map made before incarnations
    assert store.map_head("old").incarnation is None  # type: ignore[union-attr]
    assert _append(store, b"x", name="old", incarnation=None) == 1
    with pytest.raises(MapGone):
        _append(store, b"y", name="old", incarnation="i1")


def test_a_discarded_batch_is_a_tombstone_whose_version_stays_taken(store: Storage) -> None:
    _make(store)
    for payload, scans in ((b"1", 2), (b"2", 3), (b"3", 4)):
        _append(store, payload, scans=scans)
    store.discard_batch("m", 3)  # the newest: its version is not given again (a replica may have read it)
    store.discard_batch("m", 1)  # an older one
    store.discard_batch("m", 1)  # twice: nothing more to subtract
    head = store.map_head("m")
    assert head is not None and head.version == 3 and head.scans == 3
    stored = store.load_map("m")
    assert stored is not None and stored.damage == [] and stored.batches == [(2, b"2")] and stored.version == 3
    since = store.load_since("m", 0)
    assert since is not None and since.batches == [(2, b"2")] and since.damage == []
    assert _append(store, b"4") == 4
    assert _versions(store.load_map("m")) == [2, 4]
    store.discard_batch("m", 99)  # no such batch: nothing happens
    store.discard_batch("nothing", 1)


def test_a_snapshot_never_replaces_a_newer_one(store: Storage) -> None:
    _make(store)
    for k in range(1, 6):
        _append(store, str(k).encode())
    store.write_snapshot("m", 4, b"four")
    store.write_snapshot("m", 2, b"two")  # another replica's older snapshot, written late: a no-op
    store.write_snapshot("m", 4, b"four again")  # as new: a no-op as well
    stored = store.load_map("m")
    assert stored is not None and stored.damage == []
    assert (stored.snapshot_version, stored.snapshot, stored.batches) == (4, b"four", [(5, b"5")])
    assert store.map_head("m").snapshot_version == 4  # type: ignore[union-attr]
    store.write_snapshot("m", 5, b"five")
    stored = store.load_map("m")
    assert stored is not None and (stored.snapshot_version, stored.snapshot, stored.batches) == (5, b"five", [])
    assert stored.version == 5 and stored.damage == []
    store.write_snapshot("gone", 1, b"x")  # a map deleted meanwhile: nothing to do


def test_a_stale_incarnation_neither_deletes_nor_snapshots_nor_discards(store: Storage) -> None:
    _make(store, incarnation="i2")  # the map was deleted and created again by another replica
    _append(store, b"1", incarnation="i2")
    store.delete_map("m", incarnation="i1")
    store.write_snapshot("m", 1, b"stale", incarnation="i1")
    store.discard_batch("m", 1, incarnation="i1")
    stored = store.load_map("m")
    assert stored is not None and stored.snapshot is None and stored.batches == [(1, b"1")]
    store.write_snapshot("m", 1, b"own", incarnation="i2")
    assert store.load_map("m").snapshot == b"own"  # type: ignore[union-attr]
    store.delete_map("m", incarnation="i2")
    assert store.map_head("m") is None and store.map_names() == []
    store.delete_map("m")  # absent: no error


def test_load_since_gives_what_a_holder_of_an_older_version_lacks(store: Storage) -> None:
    _make(store)
    for k in range(1, 8):
        _append(store, str(k).encode())
    store.discard_batch("m", 6)
    store.write_snapshot("m", 3, b"three")
    # no newer snapshot than the holder's version: the batches after it only
    since = store.load_since("m", 4)
    assert since is not None and since.snapshot is None and since.snapshot_version == 3
    assert since.batches == [(5, b"5"), (7, b"7")] and since.version == 7 and since.damage == []
    assert since.meta == {"name": "m", "incarnation": "i1"} and since.incarnation == "i1"
    assert _versions(store.load_since("m", 3)) == [4, 5, 7]
    assert _versions(store.load_since("m", 4, up_to=5)) == [5]
    assert _versions(store.load_since("m", 7)) == []
    # a newer snapshot than the holder's version: the snapshot, then the batches after it
    since = store.load_since("m", 1)
    assert since is not None and (since.snapshot_version, since.snapshot) == (3, b"three")
    assert _versions(since) == [4, 5, 7]
    since = store.load_since("m", 0, up_to=4)
    assert since is not None and since.snapshot == b"three" and _versions(since) == [4]
    assert store.load_since("nothing", 0) is None


def test_map_heads_are_the_rows_without_payloads(store: Storage) -> None:
    assert store.map_heads() == [] and store.map_head("b") is None
    _make(store, "b", incarnation="ib")
    _make(store, "a", incarnation=None)
    _make(store, "B", incarnation="iB")
    store.append_batches([BatchRecord("b", "ib", b"x", "t5", 7), BatchRecord("b", "ib", b"y", "t6", 1)])
    store.write_snapshot("b", 1, b"s")
    assert store.map_heads() == [
        MapHead("B", {"name": "B", "incarnation": "iB"}, "t0", 0, 0, 0, "iB"),
        MapHead("a", {"name": "a", "incarnation": None}, "t0", 0, 0, 0, None),
        MapHead("b", {"name": "b", "incarnation": "ib"}, "t6", 2, 1, 8, "ib", 0, 2, 8),
    ]
    assert store.map_names() == ["B", "a", "b"]  # code point order, whatever the database's locale
    assert store.map_head("b") == store.map_heads()[2]


def test_map_head_is_fast(store: Storage) -> None:
    # called before every read on every replica
    _make(store)
    _append(store, b"x" * 100_000)
    store.write_snapshot("m", 1, b"y" * 1_000_000)  # payloads are not read
    times = []
    for _ in range(1000):
        started = time.perf_counter()
        store.map_head("m")
        times.append(time.perf_counter() - started)
    median = statistics.median(times)
    print(f"map_head median {median * 1e6:.0f} us")
    assert median < 0.002


def test_a_name_in_use_is_refused(store: Storage) -> None:
    _make(store)
    with pytest.raises(NameTaken):
        _make(store, incarnation="i2")
    assert store.map_head("m").incarnation == "i1"  # type: ignore[union-attr]


@pytest.mark.parametrize(("table", "key"), [("batches", "seq"), ("snapshots", "version")])
def test_a_changed_payload_is_damage_for_both_loaders(backend: Backend, table: str, key: str) -> None:
    store = backend.open()
    _make(store)
    for k in range(1, 4):
        _append(store, f"batch {k}".encode())
    store.write_snapshot("m", 1, b"snapshot 1")
    backend.sql(f"UPDATE {table} SET payload = ? WHERE map = 'm' AND {key} = (SELECT MAX({key}) FROM {table})",
                (b"flipped",))
    loaded = [store.load_map("m"), store.load_since("m", 0)] + ([store.load_history("m")] if table == "batches" else [])
    for stored in loaded:
        assert stored is not None and len(stored.damage) == 1 and "fails its checksum" in stored.damage[0]


@pytest.mark.parametrize(("delete", "message"), [
    ("DELETE FROM snapshots WHERE map = 'm'", "its snapshot (version 2) is missing"),
    ("DELETE FROM batches WHERE map = 'm' AND seq = 4", "its batches up to version 4 are missing"),
])
def test_rows_deleted_behind_the_stores_back_are_damage_but_tombstones_are_not(backend: Backend, delete: str,
                                                                                message: str) -> None:
    store = backend.open()
    _make(store)
    for k in range(1, 5):
        _append(store, str(k).encode())
    store.write_snapshot("m", 2, b"two")
    store.discard_batch("m", 4)  # the newest is a tombstone: it still counts as stored
    assert store.load_map("m").damage == []  # type: ignore[union-attr]
    backend.sql(delete)
    for stored in (store.load_map("m"), store.load_since("m", 3)):
        assert stored is not None and any(message in damage for damage in stored.damage), stored.damage


def test_a_batch_deleted_from_the_middle_of_the_log_is_damage(backend: Backend) -> None:
    # a gap inside the log was replayed over as if nothing were missing (only the tail was checked)
    store = backend.open()
    _make(store)
    for k in range(1, 6):
        _append(store, str(k).encode())
    store.write_snapshot("m", 1, b"one")
    store.discard_batch("m", 4)  # a tombstone keeps its version: no gap
    backend.sql("DELETE FROM batches WHERE map = 'm' AND seq = 3")
    expected = ["its batches 3 to 3 are missing (the log jumps from version 2 to 4)"]
    assert store.load_map("m").damage == expected  # type: ignore[union-attr]
    assert store.load_since("m", 1).damage == expected  # type: ignore[union-attr]
    assert store.load_since("m", 3).damage == []  # type: ignore[union-attr]  (a replica at 3 misses nothing)
    # a replica catching up to just below its own batch reads no row past the gap: the row above it tells
    assert store.load_since("m", 2, up_to=3).damage == expected  # type: ignore[union-attr]


def test_postgres_connection_loss_is_storage_unavailable_and_the_next_call_reconnects(postgres: Backend) -> None:
    # (SQLite's failures to write: tests/app/storage/test_storage_faults.py)
    store = postgres.open()
    _make(store)
    dbname = postgres.url.rsplit("/", 1)[1]

    def server_restart() -> None:  # as a restart or a failover does: every connection of the store is closed
        postgres.sql("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = ? AND pid <> "
                     "pg_backend_pid()", (dbname,))

    server_restart()
    assert store.map_head("m") is not None  # a read runs again on a new connection
    server_restart()
    with pytest.raises(StorageUnavailable):  # a write does not (it may have committed)
        _append(store, b"1")
    assert _append(store, b"1") == 1  # on a new connection; the failed call stored nothing
    with pytest.raises(StorageUnavailable):
        PostgresStorage("postgresql://postgres@127.0.0.1:1/none", timeout=1.0)


def test_postgres_replicas_creating_the_schema_at_once_all_start(postgres: Backend) -> None:
    with ThreadPoolExecutor(6) as pool:
        stores = list(pool.map(lambda _: postgres.open(), range(6)))
    _make(stores[0])
    assert all(store.map_names() == ["m"] for store in stores)


def test_a_database_from_before_the_history_counts_its_stored_batches_as_the_history(backend: Backend) -> None:
    store = backend.open()
    _make(store)
    for k in range(1, 4):
        _append(store, str(k).encode() * k, scans=k)
    store.write_snapshot("m", 3, b"three")
    store.close()
    backend.stores.remove(store)
    for statement in ("DROP TABLE bases", "ALTER TABLE batches DROP COLUMN bytes",
                      *(f"ALTER TABLE maps DROP COLUMN {column}" for column in
                        ("base_version", "history_bytes", "history_scans"))):
        backend.sql(statement)  # the schema as it was
    reopened = backend.open()
    head = reopened.map_head("m")
    assert head is not None and (head.base_version, head.history_bytes, head.history_scans) == (0, 1 + 2 + 3, 1 + 2 + 3)
    history = reopened.load_history("m")
    assert history is not None and history.damage == [] and history.snapshot is None and _versions(history) == [1, 2, 3]
    assert reopened.fold_point("m", 3) == 2 and reopened.write_base("m", 2, b"two", "i1")
    head = reopened.map_head("m")
    assert head is not None and (head.base_version, head.history_bytes, head.history_scans) == (2, 3, 3)


def test_an_old_sqlite_database_gets_the_new_columns_and_carries_on_its_versions(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite3"
    with sqlite3.connect(path) as db:  # the schema as it was: maps without versions, incarnations or scans
        db.executescript("CREATE TABLE maps (name TEXT PRIMARY KEY, meta TEXT NOT NULL, updated TEXT NOT NULL);"
                         "CREATE TABLE batches (map TEXT NOT NULL, seq INTEGER NOT NULL, payload BLOB NOT NULL,"
                         " PRIMARY KEY (map, seq));"
                         "CREATE TABLE snapshots (map TEXT PRIMARY KEY, version INTEGER NOT NULL, payload BLOB NOT NULL);"
                         "INSERT INTO maps VALUES ('m', '{}', 't0'); INSERT INTO batches VALUES ('m', 7, x'00');"
                         "INSERT INTO maps VALUES ('s', '{}', 't0'); INSERT INTO snapshots VALUES ('s', 5, x'00');")
    storage = SqliteStorage(path)
    stored = storage.load_map("m")
    assert stored is not None and stored.damage == [] and _versions(stored) == [7] and stored.version == 7
    assert storage.map_head("m") == MapHead("m", {}, "t0", 7, 0, 0, None, 0, 1, 0)  # its history: the 1-byte batch
    assert storage.map_head("s") == MapHead("s", {}, "t0", 5, 5, 0, None)
    assert _append(storage, b"y", incarnation=None) == 8  # after its newest row
    assert _append(storage, b"z", name="s", incarnation=None) == 6  # after its snapshot
    with sqlite3.connect(path) as db:
        db.execute("DELETE FROM batches WHERE seq = 8")
    assert storage.load_map("m").damage == ["its batches up to version 8 are missing (the newest stored is 7)"]  # type: ignore[union-attr]
    storage.close()


class _CommitAnswerLost:
    """A TCP proxy before PostgreSQL that, once ``armed``, forwards the next COMMIT, never relays its answer and,
    once ``committed()`` says the server has committed, drops the connection: the client cannot tell."""

    def __init__(self, target: tuple[str, int], committed: Callable[[], bool]) -> None:
        self.target, self.committed = target, committed
        self.armed, self._closing = threading.Event(), threading.Event()
        self._sockets: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._guard = threading.Lock()
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.05)
        self.port = self.listener.getsockname()[1]
        self._start(self._accept)

    def _start(self, target: Callable[..., None], *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)
        with self._guard:
            self._threads.append(thread)
        thread.start()

    def _accept(self) -> None:
        while not self._closing.is_set():
            try:
                client, _ = self.listener.accept()
            except TimeoutError:
                continue
            client.settimeout(None)
            server = socket.create_connection(self.target)
            with self._guard:
                self._sockets += [client, server]
            muted = threading.Event()  # set: the server's answers on this connection are swallowed
            self._start(self._pipe, client, server, True, muted)
            self._start(self._pipe, server, client, False, muted)

    def _pipe(self, source: socket.socket, sink: socket.socket, upstream: bool, muted: threading.Event) -> None:
        try:
            while data := source.recv(65536):
                if upstream and self.armed.is_set() and data.startswith(b"Q") and b"COMMIT" in data:
                    self.armed.clear()
                    muted.set()
                    sink.sendall(data)
                    deadline = time.monotonic() + 10
                    while not self.committed() and time.monotonic() < deadline:
                        time.sleep(0.01)
                    break
                if not (muted.is_set() and not upstream):
                    sink.sendall(data)
        except OSError:
            pass
        for end in (source, sink):  # either way both ends go: the other pipe of the pair ends too
            try:
                end.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def close(self) -> None:
        """Stop accepting, end every connection, join every thread, close every socket."""
        self._closing.set()
        with self._guard:
            sockets, threads = list(self._sockets), list(self._threads)
        threads[0].join(5)  # the accepting thread: no connection is added after it
        with self._guard:
            sockets, threads = list(self._sockets), list(self._threads)
        for end in sockets:
            try:
                end.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for thread in threads:
            thread.join(5)
        for end in [*sockets, self.listener]:
            end.close()
        assert not any(thread.is_alive() for thread in threads)


def test_a_group_whose_commit_answer_was_lost_is_answered_uncertain_and_stored_once(postgres: Backend) -> None:
    # review: a group whose COMMIT reached PostgreSQL but whose answer was lost was retried batch by batch:
    # each batch was stored twice (and fused twice by every replica) and answered as a success
    def committed() -> bool:
        return postgres.sql("SELECT count(*) FROM batches")[0][0] == 2

    parts = urlsplit(postgres.url)
    assert parts.hostname is not None and parts.port is not None
    proxy = _CommitAnswerLost((parts.hostname, parts.port), committed)
    store = committer = None
    try:
        store = PostgresStorage(urlunsplit(parts._replace(netloc=parts.netloc.replace(
            f"{parts.hostname}:{parts.port}", f"127.0.0.1:{proxy.port}"))), max_connections=2)
        for name in ("one", "two"):
            _make(store, name, incarnation=name)
        committer = GroupCommitter(store, Metrics())
        gate = threading.Event()
        committer._writer.submit(gate.wait, 10)  # the writer is busy: both batches wait and go as one group
        futures = [committer.append(BatchRecord(name, name, name.encode(), "t1", 1)) for name in ("one", "two")]
        proxy.armed.set()
        gate.set()
        for future in futures:
            exc = future.exception(30)
            assert isinstance(exc, CommitUncertain)  # a StorageUnavailable: 503 for the request
            body = error_body_of(exc)
            assert body["code"] == "STORAGE_UNAVAILABLE" and "may be stored" in body["message"]
        assert committer.append(BatchRecord("one", "one", b"next", "t2", 1)).result(30) == 2  # reconnected
    finally:
        if committer is not None:
            committer.shutdown()
        if store is not None:
            store.close()
        proxy.close()
    direct = postgres.open()
    assert _versions(direct.load_map("one")) == [1, 2] and _versions(direct.load_map("two")) == [1]  # once each
    assert direct.load_map("two").batches == [(1, b"two")]  # type: ignore[union-attr]


def test_a_batch_for_a_map_made_again_does_not_fail_the_good_batches_of_its_group(postgres: Backend) -> None:
    # review (checked, no defect): a group holding one batch for another incarnation (MapGone) is retried batch
    # by batch: the good batches are stored, the stale one alone fails
    store = postgres.open()
    for name in ("one", "two"):
        _make(store, name, incarnation=name)
    committer = GroupCommitter(store, Metrics())
    try:
        gate = threading.Event()
        committer._writer.submit(gate.wait, 10)  # the three batches wait and go as one group
        two = committer.append(BatchRecord("two", "two", b"x", "t1", 1))
        stale = committer.append(BatchRecord("one", "stale", b"y", "t1", 1))
        one = committer.append(BatchRecord("one", "one", b"z", "t1", 1))
        gate.set()
        assert isinstance(stale.exception(10), MapGone)
        assert (one.result(10), two.result(10)) == (1, 1)
    finally:
        committer.shutdown()
    assert store.load_map("one").batches == [(1, b"z")]  # type: ignore[union-attr]
    assert store.load_map("two").batches == [(1, b"x")]  # type: ignore[union-attr]


#: The SQLite schema before replicas (79276bb): no incarnations, no batch counts or stamps.
_OLD_SCHEMA = """
CREATE TABLE maps (name TEXT PRIMARY KEY, meta TEXT NOT NULL, updated TEXT NOT NULL, version INTEGER,
                   snapshot_version INTEGER);
CREATE TABLE batches (map TEXT NOT NULL REFERENCES maps(name) ON DELETE CASCADE, seq INTEGER NOT NULL,
                      payload BLOB NOT NULL, crc INTEGER, PRIMARY KEY (map, seq));
CREATE TABLE snapshots (map TEXT PRIMARY KEY REFERENCES maps(name) ON DELETE CASCADE, version INTEGER NOT NULL,
                        payload BLOB NOT NULL, crc INTEGER);
"""


def test_a_database_from_before_replicas_serves_the_same_maps(make_settings: Any, kit: Any,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    # review: a data directory written before replicas (no incarnation in the maps' metadata nor in their rows,
    # no batch counts or stamps) loads with identical risk, takes batches, and its maps can be made again
    settings = make_settings(snapshot_every=2)
    _keep_the_log_at_shutdown(monkeypatch)
    with TestClient(create_app(settings)) as client:
        for name in ("lab", "two"):
            assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
        for body in _scans(kit, 5):  # a snapshot at 4, then batch 5 in the log
            assert client.post("/maps/lab/scans", json=body).status_code == 200
        assert client.post("/maps/two/scans", json=_scans(kit, 1)[0]).status_code == 200
        risk = kit.risk_npy(client, "lab")
    path = settings.data_dir / "fuzzyrisk.sqlite3"
    with sqlite3.connect(path) as new:  # the same rows, written as the code before replicas wrote them
        maps = [(name, json.dumps({k: v for k, v in json.loads(meta).items() if k != "incarnation"}), *rest)
                for name, meta, *rest in new.execute("SELECT name, meta, updated, version, snapshot_version FROM maps")]
        # (the code before replicas kept no history: only the batches after the snapshot)
        batches = new.execute("SELECT map, seq, payload, crc FROM batches WHERE seq > COALESCE((SELECT version FROM "
                              "snapshots WHERE map = batches.map), 0)").fetchall()
        snapshots = new.execute("SELECT map, version, payload, crc FROM snapshots").fetchall()
    assert [(m, v) for m, v, *_ in batches] == [("lab", 5), ("two", 1)] and [s[:2] for s in snapshots] == [("lab", 4)]
    for leftover in settings.data_dir.glob("fuzzyrisk.sqlite3*"):
        if leftover.is_file():  # (the payload files' directory is empty: these rows are small)
            leftover.unlink()
    with sqlite3.connect(path) as old:
        old.executescript(_OLD_SCHEMA)
        old.executemany("INSERT INTO maps VALUES (?, ?, ?, ?, ?)", maps)
        old.executemany("INSERT INTO batches VALUES (?, ?, ?, ?)", batches)
        old.executemany("INSERT INTO snapshots VALUES (?, ?, ?, ?)", snapshots)

    with TestClient(create_app(settings)) as client:
        assert client.get("/ready").json()["maps_quarantined"] == []
        np.testing.assert_array_equal(kit.risk_npy(client, "lab"), risk)
        etag = client.get("/maps/lab/risk", params={"format": "npy"}).headers["ETag"]
        assert [(m["name"], m["version"], m["scans_fused"]) for m in client.get("/maps").json()] == \
            [("lab", 5, 5), ("two", 1, 1)]
    with TestClient(create_app(settings)) as client:  # a restart on it: the same version, the same ETag
        assert client.get("/maps/lab/risk", params={"format": "npy"}).headers["ETag"] == etag
        assert client.post("/maps/lab/scans", json=_scans(kit, 7)[6]).json()["version"] == 6
        assert client.get("/maps/lab/export/mcap").status_code == 200
        assert client.delete("/maps/two").status_code == 204
        assert client.post("/maps", json={**kit.MAP_2D, "name": "two"}).status_code == 201
        risk = kit.risk_npy(client, "lab")
    with TestClient(create_app(settings)) as client:
        assert client.get("/ready").json()["maps_quarantined"] == []
        assert (kit.version(client, "lab"), kit.version(client, "two")) == (6, 0)
        np.testing.assert_array_equal(kit.risk_npy(client, "lab"), risk)


def test_a_map_is_snapshotted_once_its_log_walks_the_cell_limit(make_client: Any, make_settings: Any,
                                                                kit: Any) -> None:
    # 28 scans of 2 M beams, under the byte limit, made a restart replay 52-56 s of fusion
    bodies = [{"scans": [kit.laser(beams=2_000, wall=2.0 + 0.1 * k)]} for k in range(6)]
    spec = GridSpec(origin=tuple(kit.MAP_2D["origin"]), size=tuple(kit.MAP_2D["size"]),
                    resolution=kit.MAP_2D["resolution"])
    walked = np.cumsum([cast_work(spec, [LaserScan(pose=(0.0, 0.0, 0.0), angle_min=s["angle_min"],
                                                   angle_increment=s["angle_increment"], ranges=np.array(s["ranges"]),
                                                   range_min=s["range_min"], range_max=s["range_max"])])
                        for s in (body["scans"][0] for body in bodies)])
    limit = int(walked[2]) - 1  # crossed by the third batch
    client = make_client(snapshot_every=1000, snapshot_log_cells=limit)
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    for k, body in enumerate(bodies, start=1):
        assert client.post("/maps/lab/scans", json=body).status_code == 200
        kit.snapshots_stored(client)
        if _rows(data_dir, "snapshots"):
            break
    assert _rows(data_dir, "snapshots") == [("lab", 3)] and _rows(data_dir, "batches") == [("lab", 1), ("lab", 2),
                                                                                          ("lab", 3)]
    risk = kit.risk_npy(client, "lab")
    client.__exit__(None, None, None)
    assert kit.risk_npy(make_client(), "lab").tobytes() == risk.tobytes()
