"""Durable storage: maps survive restarts bit for bit, snapshots plus replay, deletes, refused batches."""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app
from app.storage import SqliteStorage, StorageUnavailable
from fuzzyocc import FuzzyMap
from tests.conftest import error_message


def _rows(data_dir: Path, table: str) -> list[tuple[Any, ...]]:
    with sqlite3.connect(data_dir / "fuzzyrisk.sqlite3") as db:
        column = "seq" if table == "batches" else "version"
        return db.execute(f"SELECT map, {column} FROM {table} ORDER BY map, {column}").fetchall()


def _scans(kit: Any, n: int) -> list[dict[str, Any]]:
    return [{"scans": [kit.laser(x=0.1 * k, y=-0.2 * k, theta=0.3 * k, wall=2.05 + 0.1 * k)]} for k in range(n)]


@pytest.mark.parametrize("model", ["fuzzy", "bayes"])
def test_a_restart_serves_the_same_maps_bit_for_bit(make_client: Any, kit: Any, model: str) -> None:
    first = make_client()
    first.post("/maps", json={**kit.MAP_2D, "model": model})
    for body in _scans(kit, 5):
        assert first.post("/maps/lab/scans", json=body).status_code == 200
    info, risk = first.get("/maps/lab").json(), kit.risk_npy(first, "lab")
    first.__exit__(None, None, None)

    second = make_client()
    assert second.get("/maps/lab").json() == info
    assert kit.risk_npy(second, "lab").tobytes() == risk.tobytes()


def test_snapshots_drop_the_batches_they_cover_and_replay_the_rest(make_client: Any, make_settings: Any,
                                                                   kit: Any) -> None:
    client = make_client(snapshot_every=3)
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    for body in _scans(kit, 7):
        client.post("/maps/lab/scans", json=body)
    assert _rows(data_dir, "snapshots") == [("lab", 6)]
    assert _rows(data_dir, "batches") == [("lab", 7)]
    risk = kit.risk_npy(client, "lab")

    # a crash image: the files as they are on disk now, while the service still runs
    crashed = data_dir.parent / "crashed"
    shutil.copytree(data_dir, crashed)
    replayed = TestClient(create_app(Settings(data_dir=crashed, plan_warmup=False)))
    with replayed:
        assert replayed.get("/maps/lab").json()["version"] == 7
        assert kit.risk_npy(replayed, "lab").tobytes() == risk.tobytes()


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


def test_a_graceful_stop_snapshots_every_map(make_client: Any, make_settings: Any, kit: Any) -> None:
    client = make_client()
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    for body in _scans(kit, 2):
        client.post("/maps/lab/scans", json=body)
    client.__exit__(None, None, None)
    assert _rows(data_dir, "snapshots") == [("lab", 2)] and _rows(data_dir, "batches") == []


def test_deleting_a_map_removes_its_rows_for_good(make_client: Any, make_settings: Any, kit: Any) -> None:
    client = make_client(snapshot_every=2)
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    client.post("/maps", json={**kit.MAP_2D, "name": "kept"})
    for body in _scans(kit, 3):
        client.post("/maps/lab/scans", json=body)
    assert client.delete("/maps/lab").status_code == 204
    assert _rows(data_dir, "batches") == [] and _rows(data_dir, "snapshots") == []
    client.__exit__(None, None, None)
    again = make_client()
    assert [m["name"] for m in again.get("/maps").json()] == ["kept"]
    assert again.post("/maps", json=kit.MAP_2D).json()["version"] == 0  # the name is free, the map new


def test_a_refused_batch_leaves_nothing_on_disk(lab: TestClient, make_settings: Any, kit: Any) -> None:
    lab.post("/maps/lab/scans", json={"scans": [kit.laser(), {**kit.laser(), "angle_increment": 0}]})
    assert _rows(make_settings().data_dir, "batches") == []


def test_a_batch_that_fails_while_applied_is_not_kept(make_settings: Any, kit: Any,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    settings = make_settings()
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        client.post("/maps", json=kit.MAP_2D)
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 200

        def broken(self: FuzzyMap, scans: Any) -> Any:
            raise MemoryError("simulated")

        monkeypatch.setattr(FuzzyMap, "integrate_batch", broken)
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 500
        assert _rows(settings.data_dir, "batches") == [("lab", 1)]
        assert client.get("/maps/lab").json()["version"] == 1
        monkeypatch.undo()
        # version 2 stays taken (services.py: a failed batch's version is never reused), so the map skips it
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).json()["version"] == 3


def test_a_batch_that_fails_half_way_leaves_the_live_map_as_a_restart_rebuilds_it(
        make_settings: Any, kit: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    # issue 11: a MemoryError after part of a batch was fused left the live map changed in part
    settings = make_settings()
    original = FuzzyMap.integrate_batch
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        client.post("/maps", json=kit.MAP_2D)
        assert client.post("/maps/lab/scans", json=_scans(kit, 1)[0]).status_code == 200
        before = client.get("/maps/lab/risk", params={"format": "npy"}).content

        failed: list[bool] = []

        def half(self: FuzzyMap, scans: Any) -> Any:
            if self.spec.shape == (100, 100) and not failed:  # the test's map, once (the rebuild replays)
                failed.append(True)
                original(self, list(scans)[:1])  # the first scan changes the map...
                raise MemoryError("simulated")  # ...then the batch fails
            return original(self, scans)

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

    def write_snapshot(self: SqliteStorage, name: str, version: int, payload: bytes) -> None:
        if version % 2:  # the service's own every-2 snapshots (snapshot_every=2) pass
            raise StorageUnavailable("database or disk is full")
        original(self, name, version, payload)

    monkeypatch.setattr(SqliteStorage, "write_snapshot", write_snapshot)


def _flip_a_bit(data_dir: Path, table: str, key: str, name: str) -> None:
    with sqlite3.connect(data_dir / "fuzzyrisk.sqlite3") as db:
        (payload,) = db.execute(f"SELECT payload FROM {table} WHERE map = ? ORDER BY {key} LIMIT 1", (name,)).fetchone()
        damaged = bytearray(payload)
        damaged[len(damaged) // 2] ^= 0x04
        db.execute(f"UPDATE {table} SET payload = ? WHERE map = ? AND {key} = "
                   f"(SELECT {key} FROM {table} WHERE map = ? ORDER BY {key} LIMIT 1)", (bytes(damaged), name, name))


@pytest.mark.parametrize(("table", "key", "what"), [("batches", "seq", "batch 1"), ("snapshots", "version", "snapshot")])
def test_a_damaged_row_quarantines_its_map_and_the_others_start(make_settings: Any, kit: Any, table: str,
                                                                 key: str, what: str,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # issue 11: a flipped bit in a stored batch was fused as if nothing happened; a damaged snapshot
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


def test_map_metadata_survives_a_restart(make_client: Any, kit: Any) -> None:
    first = make_client()
    created = first.post("/maps", json={**kit.MAP_3D, "model": "bayes",
                                         "sensor": {"range_sigma": 0.07, "registration_sigma": 0.02,
                                                    "range_sigma_per_m": 0.01}}).json()
    first.__exit__(None, None, None)
    assert make_client().get("/maps/hall").json() == created


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
    from app.backup import main as backup_main

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
    # issue 11: a start read every batch of every map at once (377 MB of log peaked at 1.1 GB); now
    # maps load one at a time, so the peak follows the largest map, not their sum
    import asyncio
    import tracemalloc

    from app import batches
    from app.metrics import Metrics
    from app.schemas import ScanBatch
    from app.services import MapService
    from app.storage import BatchRecord, SqliteStorage

    names = [f"m{k}" for k in range(8)]
    client = make_client()
    for name in names:
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    client.__exit__(None, None, None)
    settings = make_settings()
    limits = batches.Limits(max_scans=256, max_rays=settings.max_rays_per_scan)
    # many small batches: the log's bytes, not one batch's fusion scratch, make the peak
    payload = batches.encode(batches.from_json(ScanBatch.model_validate({"scans": [kit.laser(beams=20_000)]}), 2,
                                               limits))
    per_map = 50
    storage = SqliteStorage(settings.database_path)
    storage.append_batches([BatchRecord(name, version, payload, "2026-12-02T00:00:00+00:00")
                            for name in names for version in range(1, per_map + 1)])
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
        versions = sum(service.maps.get_map(name).version for name in names)
        await service.stop()
        return peak, versions

    peak, versions = asyncio.run(start())
    assert versions == per_map * len(names)  # every batch replayed
    print(f"start peak {peak / 1e6:.1f} MB for {total / 1e6:.1f} MB of log")
    assert peak < total / 2, (peak, total)


def test_a_map_is_snapshotted_once_its_log_holds_the_byte_limit(make_client: Any, make_settings: Any,
                                                                kit: Any) -> None:
    # issue 11: the log of one map was bounded by a count of batches only (200 x 64 MiB = 12.5 GiB)
    client = make_client(snapshot_every=1000, snapshot_log_bytes=20_000)
    data_dir = make_settings().data_dir
    client.post("/maps", json=kit.MAP_2D)
    big = [{"scans": [kit.laser(beams=1_000, wall=2.0 + 0.1 * k)]} for k in range(6)]  # about 8 kB logged each
    for k, body in enumerate(big, start=1):
        assert client.post("/maps/lab/scans", json=body).status_code == 200
        snapshots = _rows(data_dir, "snapshots")
        if snapshots:
            break
    assert snapshots == [("lab", k)] and 2 <= k <= 4  # the batch that crossed 20,000 bytes of log
    assert _rows(data_dir, "batches") == []  # dropped with the snapshot
    risk = kit.risk_npy(client, "lab")
    client.__exit__(None, None, None)
    assert kit.risk_npy(make_client(), "lab").tobytes() == risk.tobytes()


@pytest.mark.parametrize(("delete", "message"), [
    ("DELETE FROM snapshots WHERE map = 'lab'", "its snapshot (version 2) is missing"),
    ("DELETE FROM batches WHERE map = 'lab' AND seq = 3", "its batches up to version 3 are missing"),
])
def test_rows_deleted_behind_the_services_back_quarantine_the_map(make_settings: Any, kit: Any, delete: str,
                                                                  message: str,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    # issue 11: a deleted snapshot row left a map without batches 1-2 reporting version 3
    settings = make_settings(snapshot_every=2)
    _keep_the_log_at_shutdown(monkeypatch)
    with TestClient(create_app(settings)) as client:
        client.post("/maps", json=kit.MAP_2D)
        for body in _scans(kit, 3):  # a snapshot at version 2, batch 3 after it
            assert client.post("/maps/lab/scans", json=body).status_code == 200
    monkeypatch.undo()
    with sqlite3.connect(settings.data_dir / "fuzzyrisk.sqlite3") as db:
        db.execute(delete)
    with TestClient(create_app(settings)) as client:
        damaged = client.get("/maps/lab")
        assert damaged.status_code == 503 and message in error_message(damaged)
        assert client.get("/ready").json()["maps_quarantined"] == ["lab"]


def test_a_batch_discarded_by_the_service_is_not_damage(tmp_path: Path) -> None:
    # a batch that failed to apply is removed from the log by the service itself: its version is skipped
    from app.storage import SqliteStorage

    storage = SqliteStorage(tmp_path / "db.sqlite3")
    storage.create_map("m", {"model": "fuzzy"}, "t0")
    for version in (1, 2, 3):
        storage.append_batch("m", version, b"x", "t1")
    storage.discard_batch("m", 3)  # the newest: the map's record goes back to 2
    storage.discard_batch("m", 1)  # an older one (later ones committed meanwhile): a skipped version
    stored = storage.load_map("m")
    assert stored is not None and stored.damage == [] and [v for v, _ in stored.batches] == [2]
    storage.append_batch("m", 4, b"y", "t2")
    assert storage.load_map("m").damage == []  # type: ignore[union-attr]
    storage.close()


def test_a_database_from_before_the_version_record_loads_unchecked(tmp_path: Path) -> None:
    from app.storage import SqliteStorage

    path = tmp_path / "old.sqlite3"
    with sqlite3.connect(path) as db:  # the schema as it was: maps without their versions
        db.executescript("CREATE TABLE maps (name TEXT PRIMARY KEY, meta TEXT NOT NULL, updated TEXT NOT NULL);"
                         "CREATE TABLE batches (map TEXT NOT NULL, seq INTEGER NOT NULL, payload BLOB NOT NULL,"
                         " PRIMARY KEY (map, seq));"
                         "CREATE TABLE snapshots (map TEXT PRIMARY KEY, version INTEGER NOT NULL, payload BLOB NOT NULL);"
                         "INSERT INTO maps VALUES ('m', '{}', 't0'); INSERT INTO batches VALUES ('m', 7, x'00');")
    storage = SqliteStorage(path)
    stored = storage.load_map("m")
    assert stored is not None and stored.damage == [] and [v for v, _ in stored.batches] == [7]
    storage.append_batch("m", 8, b"y", "t1")  # from now on the map's record is kept
    with sqlite3.connect(path) as db:
        db.execute("DELETE FROM batches WHERE seq = 8")
    assert storage.load_map("m").damage == ["its batches up to version 8 are missing (the newest stored is 7)"]  # type: ignore[union-attr]
    storage.close()
