"""Replicas of the service on one PostgreSQL database (issue 14): every replica serves every map.

Each test runs two services (two apps, their own data directories) on one fresh database of a real
PostgreSQL server (``tests/pgserver.py``), as two replicas behind a load balancer would.
"""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.mapstate import restore
from app.storage_pg import PostgresStorage
from tests.conftest import error_message

Replicas = Callable[..., tuple[TestClient, TestClient]]


@pytest.fixture
def replicas(make_client: Callable[..., TestClient], postgres_server: Any, tmp_path: Path) -> Replicas:
    """Two replicas on one new database; ``url`` of it on the function as ``replicas.url``."""

    def make(**overrides: Any) -> tuple[TestClient, TestClient]:
        url = postgres_server.create_database()
        make.url = url  # type: ignore[attr-defined]
        return (make_client(data_dir=tmp_path / "a", database_url=url, **overrides),
                make_client(data_dir=tmp_path / "b", database_url=url, **overrides))

    return make


def _scan(kit: Any, k: int) -> dict[str, Any]:
    """A different view of the lab's wall for each ``k``."""
    return kit.laser(x=-1.0 + 0.05 * (k % 20), y=-1.0 + 0.1 * (k % 7), theta=0.03 * k, wall=3.0 + 0.01 * k)


def test_a_batch_acknowledged_by_one_replica_is_read_by_the_other(replicas: Replicas, kit: Any) -> None:
    a, b = replicas()
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert b.get("/maps/lab").json()["version"] == 0  # made on a, served by b
    for k in range(3):
        assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, k)]}).status_code == 200
    assert b.get("/maps/lab").json()["version"] == 3
    assert b.get("/maps/lab").headers["X-Map-Version"] == "3"
    np.testing.assert_array_equal(kit.risk_npy(a, "lab"), kit.risk_npy(b, "lab"))
    # and back: b's batch is a's next read
    assert b.post("/maps/lab/scans", json={"scans": [_scan(kit, 9)]}).json()["version"] == 4
    assert kit.version(a, "lab") == 4
    np.testing.assert_array_equal(kit.risk_npy(a, "lab"), kit.risk_npy(b, "lab"))
    assert a.get("/maps/lab/risk", params={"format": "npy"}).headers["ETag"] == \
        b.get("/maps/lab/risk", params={"format": "npy"}).headers["ETag"]


def test_batches_sent_to_both_replicas_at_once_take_one_order_and_give_identical_maps(
        replicas: Replicas, kit: Any) -> None:
    a, b = replicas()
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    acknowledged: list[int] = []
    errors: list[str] = []

    def send(client: TestClient, first: int) -> None:
        for k in range(first, first + 15):
            response = client.post("/maps/lab/scans", json={"scans": [_scan(kit, k)]})
            if response.status_code != 200:
                errors.append(response.text)
            else:
                acknowledged.append(response.json()["version"])

    threads = [threading.Thread(target=send, args=(client, first)) for client, first in
               ((a, 0), (b, 100), (a, 200), (b, 300))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert sorted(acknowledged) == list(range(1, 61))  # one order for the map, decided by the database
    risk_a, risk_b = kit.risk_npy(a, "lab"), kit.risk_npy(b, "lab")
    np.testing.assert_array_equal(risk_a, risk_b)
    # and the log is the truth: replayed from the database, the map is the one both replicas serve
    store = PostgresStorage(replicas.url)  # type: ignore[attr-defined]
    try:
        stored = store.load_map("lab")
        assert stored is not None and [v for v, _ in stored.batches] == list(range(1, 61))
        np.testing.assert_array_equal(restore(stored).map.risk(), risk_a)
    finally:
        store.close()
    assert a.get("/maps/lab").json()["scans_fused"] == b.get("/maps/lab").json()["scans_fused"] == 60


def test_a_replica_catches_up_from_a_snapshot_another_replica_wrote(replicas: Replicas, kit: Any) -> None:
    a, b = replicas(snapshot_every=4)
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert b.post("/maps/lab/scans", json={"scans": [_scan(kit, 0)]}).status_code == 200  # b holds version 1
    for k in range(1, 9):  # a snapshots at 4 and 8: batches 1-8 leave the log
        assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, k)]}).status_code == 200
    store = PostgresStorage(replicas.url)  # type: ignore[attr-defined]
    try:
        stored = store.load_map("lab")
        assert stored is not None and stored.snapshot_version == 8 and [v for v, _ in stored.batches] == [9]
    finally:
        store.close()
    assert kit.version(b, "lab") == 9
    assert b.app.state.service.maps.entry("lab").snapshot_version == 8  # type: ignore[attr-defined]
    np.testing.assert_array_equal(kit.risk_npy(a, "lab"), kit.risk_npy(b, "lab"))


def test_a_map_deleted_through_one_replica_is_gone_from_the_other(replicas: Replicas, kit: Any) -> None:
    a, b = replicas()
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert b.post("/maps/lab/scans", json={"scans": [_scan(kit, 0)]}).status_code == 200
    assert a.delete("/maps/lab").status_code == 204
    response = b.get("/maps/lab/risk", params={"format": "npy"})
    assert response.status_code == 404, response.text
    response = b.post("/maps/lab/scans", json={"scans": [_scan(kit, 1)]})
    assert response.status_code == 404 and "lab" in error_message(response)
    assert b.get("/maps").json() == []
    # made again, with another grid, through the other replica: served as the new map everywhere
    assert b.post("/maps", json={**kit.MAP_2D, "resolution": 0.2}).status_code == 201
    assert a.get("/maps/lab").json()["resolution"] == 0.2
    assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 2)]}).json()["version"] == 1
    assert kit.risk_npy(b, "lab").shape == (50, 50)


def test_a_batch_for_a_map_made_again_through_another_replica_stores_nothing(replicas: Replicas, kit: Any) -> None:
    a, b = replicas()
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 0)]}).status_code == 200  # a holds the first one
    assert b.delete("/maps/lab").status_code == 204
    assert b.post("/maps", json=kit.MAP_2D).status_code == 201
    response = a.post("/maps/lab/scans", json={"scans": [_scan(kit, 1)]})
    assert response.status_code == 409, response.text  # never fused into the new map under the old one's name
    assert kit.version(b, "lab") == 0
    assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 1)]}).json()["version"] == 1  # now the new one


def test_a_replica_holds_only_the_maps_it_serves(replicas: Replicas, kit: Any) -> None:
    a, b = replicas(map_idle_s=0.5)
    for name in ("one", "two", "three"):
        assert a.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    assert b.get("/ready").json()["maps_loaded"] == 0
    assert [m["name"] for m in b.get("/maps").json()] == ["one", "three", "two"]
    assert b.get("/ready").json()["maps_loaded"] == 0  # listed from the database, not loaded
    assert b.get("/maps/two/risk", params={"format": "npy"}).status_code == 200
    assert b.get("/ready").json()["maps_loaded"] == 1
    b.app.state.service.maps.evict_idle()  # type: ignore[attr-defined]
    assert b.get("/ready").json()["maps_loaded"] == 1  # used just now
    time.sleep(0.6)
    assert b.app.state.service.maps.evict_idle() == 1  # type: ignore[attr-defined]
    assert b.get("/ready").json()["maps_loaded"] == 0
    assert b.get("/maps/two").json()["version"] == 0  # loaded again when asked for


def test_the_map_count_limit_counts_every_replicas_maps(replicas: Replicas, kit: Any) -> None:
    a, b = replicas(max_maps=2)
    assert a.post("/maps", json={**kit.MAP_2D, "name": "one"}).status_code == 201
    assert b.post("/maps", json={**kit.MAP_2D, "name": "two"}).status_code == 201
    response = a.post("/maps", json={**kit.MAP_2D, "name": "three"})
    assert response.status_code == 507 and "FUZZYRISK_MAX_MAPS" in error_message(response)
    assert b.post("/maps", json={**kit.MAP_2D, "name": "one"}).status_code == 409  # taken through a


def test_a_new_replica_serves_what_the_others_acknowledged(replicas: Replicas, kit: Any,
                                                           make_client: Callable[..., TestClient],
                                                           tmp_path: Path) -> None:
    a, b = replicas(snapshot_every=3)
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    for k in range(7):  # snapshots by both, batches after them
        assert (a if k % 2 else b).post("/maps/lab/scans", json={"scans": [_scan(kit, k)]}).status_code == 200
    c = make_client(data_dir=tmp_path / "c", database_url=replicas.url)  # type: ignore[attr-defined]
    assert kit.version(c, "lab") == 7
    np.testing.assert_array_equal(kit.risk_npy(c, "lab"), kit.risk_npy(a, "lab"))
    np.testing.assert_array_equal(kit.risk_npy(c, "lab"), kit.risk_npy(b, "lab"))


def test_a_batch_already_in_another_replicas_snapshot_is_not_fused_twice(replicas: Replicas, kit: Any) -> None:
    # a holds the map at version 0 and commits batch 3 behind b's 1 and 2; before a applies it, b fuses it
    # (b catches up on committed batches) with its own 4 and snapshots at 4: a's catch-up then lands on that
    # snapshot, which holds a's batch already
    a, b = replicas(snapshot_every=2)
    assert b.post("/maps", json=kit.MAP_2D).status_code == 201
    assert kit.version(a, "lab") == 0  # a holds it now, at version 0
    for k in (1, 2):
        assert b.post("/maps/lab/scans", json={"scans": [_scan(kit, k)]}).status_code == 200
    writes = a.app.state.service.writes  # type: ignore[attr-defined]
    original, gate, entered = writes._catch_up_locked, threading.Event(), threading.Event()

    async def held_back(entry: Any, target: int) -> None:
        entered.set()
        await asyncio.get_running_loop().run_in_executor(None, gate.wait, 10)
        await original(entry, target)

    writes._catch_up_locked = held_back
    with ThreadPoolExecutor(1) as pool:
        mine = pool.submit(a.post, "/maps/lab/scans", json={"scans": [_scan(kit, 3)]})
        assert entered.wait(10)  # a's batch is committed as 3, its catch-up held
        assert b.post("/maps/lab/scans", json={"scans": [_scan(kit, 4)]}).json()["version"] == 4
        gate.set()
        assert mine.result().json()["version"] == 3
    held = a.app.state.service.maps.entry("lab")  # type: ignore[attr-defined]
    assert (held.version, held.scans_fused) == (4, 4)  # as the snapshot holds it (before any read)
    np.testing.assert_array_equal(kit.risk_npy(a, "lab"), kit.risk_npy(b, "lab"))
    assert a.get("/maps/lab").json()["scans_fused"] == 4
