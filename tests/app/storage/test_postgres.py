"""Replicas of the service on one PostgreSQL database: every replica serves every map.

Each test runs two services (two apps, their own data directories) on one fresh database of a real
PostgreSQL server (``tests/pgserver.py``), as two replicas behind a load balancer would.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import psycopg
import pytest
from fastapi.testclient import TestClient

from app.ros import bagsize
from app.api.factory import create_app
from app.maps import restore
from app.storage.postgres import PostgresStorage
from tests.app.api.routes.test_maps import PAPER_BUT_NO_RETURNS_CUT, settings_of
from tests.app.cli.test_import_bag import laser_scenario, upload, write_bag
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
    for k in range(1, 9):  # a snapshots at 4 and 8: b, at version 1, catches up from the one at 8
        assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, k)]}).status_code == 200
    kit.snapshots_stored(a)
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
    assert b.app.state.service.maps.evict_idle() == 0  # type: ignore[attr-defined]  # used just now
    assert b.get("/ready").json()["maps_loaded"] == 1
    # the replica's own eviction (every FUZZYRISK_MAP_IDLE_S / 2) drops it once idle that long
    deadline = time.monotonic() + 10
    while b.get("/ready").json()["maps_loaded"] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert b.get("/ready").json()["maps_loaded"] == 0
    assert b.get("/maps/two").json()["version"] == 0  # loaded again when asked for


def test_a_replica_lists_a_map_it_does_not_hold_with_settings_that_make_the_same_map(replicas: Replicas,
                                                                                       kit: Any) -> None:
    a, b = replicas()
    body = {**kit.MAP_2D, "engine": PAPER_BUT_NO_RETURNS_CUT, "frame_id": "robot1/map", "resolution": 1 / 3}
    assert a.post("/maps", json=body).status_code == 201
    shown = a.get("/maps/lab").json()
    (listed,) = b.get("/maps").json()  # from the stored row: b holds no map
    assert b.get("/ready").json()["maps_loaded"] == 0
    # what only the holder knows (the cells held, the bounds of what was observed) is null in b's list
    assert listed["held_cells"] is None and listed["bounds"] is None
    assert {**listed, "held_cells": shown["held_cells"], "bounds": shown["bounds"]} == shown
    assert b.post("/maps", json={**settings_of(listed), "name": "copy"}).status_code == 201
    assert settings_of(a.get("/maps/copy").json()) == settings_of(shown)


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
        kit.snapshots_stored(b)
        gate.set()
        assert mine.result().json()["version"] == 3
    held = a.app.state.service.maps.entry("lab")  # type: ignore[attr-defined]
    assert (held.version, held.scans_fused) == (4, 4)  # as the snapshot holds it (before any read)
    np.testing.assert_array_equal(kit.risk_npy(a, "lab"), kit.risk_npy(b, "lab"))
    assert a.get("/maps/lab").json()["scans_fused"] == 4


# --- the review of the fleet mode (docs/DESIGN.md 6.1): each test holds a defect it found, fixed since ---


def test_a_first_read_loading_a_map_made_again_meanwhile_misses_no_acknowledged_batch(
        replicas: Replicas, kit: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    # review: a read's first load could land on a map made again meanwhile and take the old map's newest version
    # as caught up: the new map's batches were then missing from reads, fused around, and erased by a snapshot
    a, b = replicas(snapshot_every=4)
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    for k in range(3):  # the first map of the name reaches version 3
        assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, k)]}).status_code == 200
    storage = b.app.state.service.storage  # type: ignore[attr-defined]
    load_map, made_again = storage.load_map, []

    def made_again_first(name: str) -> Any:  # between b's look at the map's newest version and its load
        if not made_again:
            made_again.append(name)
            assert a.delete("/maps/lab").status_code == 204
            assert a.post("/maps", json=kit.MAP_2D).status_code == 201
        return load_map(name)

    monkeypatch.setattr(storage, "load_map", made_again_first)
    assert b.get("/maps/lab").json()["version"] == 0 and made_again  # b loaded the new map
    for k in range(3):
        assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 10 + k)]}).json()["version"] == k + 1
    assert kit.version(b, "lab") == 3  # every batch a acknowledged
    assert b.post("/maps/lab/scans", json={"scans": [_scan(kit, 20)]}).json()["version"] == 4  # snapshot at 4
    risk = kit.risk_npy(a, "lab")
    np.testing.assert_array_equal(kit.risk_npy(b, "lab"), risk)
    assert a.get("/maps/lab").json()["scans_fused"] == b.get("/maps/lab").json()["scans_fused"] == 4
    store = PostgresStorage(replicas.url)  # type: ignore[attr-defined]
    try:  # and a replica loading it now (from b's snapshot) serves the same 4 scans
        stored = store.load_map("lab")
        assert stored is not None and stored.snapshot_version == 4
        replayed = restore(stored).map
        assert replayed.scans_fused == 4
        np.testing.assert_array_equal(replayed.risk(), risk)
    finally:
        store.close()


def test_the_list_leaves_out_a_map_whose_stored_metadata_is_unusable(replicas: Replicas, kit: Any) -> None:
    # review: one map whose stored metadata could not be used made GET /maps a 500 on every replica
    a, b = replicas()
    for name in ("lab", "bad"):
        assert a.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    with psycopg.connect(replicas.url, autocommit=True) as db:  # type: ignore[attr-defined]
        (text,) = db.execute("SELECT meta FROM maps WHERE name = 'bad'").fetchone()  # type: ignore[misc]
        meta = {**json.loads(text), "engine": {"definition": {"not": "an engine"}}}
        db.execute("UPDATE maps SET meta = %s WHERE name = 'bad'", (json.dumps(meta),))
    for client in (a, b):
        listed = client.get("/maps")
        assert listed.status_code == 200 and [m["name"] for m in listed.json()] == ["lab"]
    for route in ("/maps/bad", "/maps/bad/risk"):
        response = b.get(route)
        assert response.status_code == 503 and "quarantined" in error_message(response)
    assert b.get("/ready").json()["maps_quarantined"] == ["bad"]
    assert kit.version(b, "lab") == 0  # the others are served


def test_a_delete_with_a_read_of_the_map_in_between_answers_204(replicas: Replicas, kit: Any,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # review: a read while the delete's rows went found no row and dropped the map; the delete then failed (500)
    a, _ = replicas()
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert a.get("/maps/lab").status_code == 200  # held by a
    storage = a.app.state.service.storage  # type: ignore[attr-defined]
    delete_map, meanwhile = storage.delete_map, []

    def read_meanwhile(*args: Any) -> None:
        delete_map(*args)
        meanwhile.append(a.get("/maps/lab").status_code)

    monkeypatch.setattr(storage, "delete_map", read_meanwhile)
    assert a.delete("/maps/lab").status_code == 204
    assert meanwhile == [404]
    assert a.get("/maps/lab").status_code == 404 and a.get("/maps").json() == []
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201


def test_a_replica_holding_a_copy_of_a_map_deleted_elsewhere_creates_it_again(replicas: Replicas, kit: Any) -> None:
    # review: b refused (409) to create a map deleted through a while it still held its copy of the old one
    a, b = replicas()
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert b.get("/maps/lab").status_code == 200  # b holds it
    assert a.delete("/maps/lab").status_code == 204
    assert b.get("/maps").json() == []
    created = b.post("/maps", json={**kit.MAP_2D, "resolution": 0.2})  # a balancer sends the new one to b
    assert created.status_code == 201, created.text
    for client in (b, a):
        assert client.get("/maps/lab").json()["resolution"] == 0.2
    assert b.post("/maps/lab/scans", json={"scans": [_scan(kit, 0)]}).json()["version"] == 1
    assert kit.risk_npy(b, "lab").shape == (50, 50)


def test_a_bag_import_keeps_its_map_in_memory_while_another_map_is_asked_for(
        replicas: Replicas, kit: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # review: once its body was spooled, a bag upload did not count as a use of its map: a load of another map
    # dropped it to make room, and the import's first batch found another copy and answered 409
    _, b = replicas(max_total_cells=15_000)  # room for one 100 x 100 bayes map (it holds its whole box)
    for name in ("bag", "other"):
        assert b.post("/maps", json={**kit.MAP_2D, "model": "bayes", "name": name}).status_code == 201
    bag = write_bag(laser_scenario(), tmp_path / "drive", "ros1")
    decompressed_bytes, meanwhile = bagsize.decompressed_bytes, []

    def other_read_meanwhile(path: Path) -> int:  # while the spooled bag is checked, a client reads another map
        meanwhile.append(b.get("/maps/other"))
        return decompressed_bytes(path)

    monkeypatch.setattr(bagsize, "decompressed_bytes", other_read_meanwhile)
    imported = upload(b, "bag", bag)
    assert imported.status_code == 200, imported.text
    assert imported.json()["complete"] and imported.json()["scans_fused"] > 0
    assert kit.version(b, "bag") == imported.json()["version"]
    (other,) = meanwhile
    assert other.status_code == 507 and "FUZZYRISK_MAX_TOTAL_CELLS" in error_message(other)  # bag was in use
    assert b.get("/maps/other").status_code == 200  # the import over, bag makes room


def test_maps_loading_at_once_count_in_the_memory_limit(replicas: Replicas, kit: Any,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    # review: the room for a map was checked before its load's awaits: maps loading at once all passed the
    # check and together held more than FUZZYRISK_MAX_TOTAL_CELLS
    a, b = replicas(max_total_cells=15_000)  # room for one 100 x 100 bayes map (it holds its whole box)
    for name in ("one", "two"):
        assert a.post("/maps", json={**kit.MAP_2D, "model": "bayes", "name": name}).status_code == 201
    storage = b.app.state.service.storage  # type: ignore[attr-defined]
    load_map, loading, gate = storage.load_map, threading.Event(), threading.Event()

    def held_back(name: str) -> Any:  # a load that takes a while (a long log, a slow database)
        loading.set()
        gate.wait(10)
        return load_map(name)

    monkeypatch.setattr(storage, "load_map", held_back)
    with ThreadPoolExecutor(1) as pool:
        first = pool.submit(b.get, "/maps/one")
        assert loading.wait(10)
        second = b.get("/maps/two")  # while "one" loads
        gate.set()
        assert first.result().status_code == 200
    assert second.status_code == 507 and "FUZZYRISK_MAX_TOTAL_CELLS" in error_message(second)
    maps = b.app.state.service.maps  # type: ignore[attr-defined]
    assert [entry.name for entry in maps.held_maps] == ["one"]
    assert b.get("/maps/two").status_code == 200  # "one" loaded and idle: dropped to make room
    assert [entry.name for entry in maps.held_maps] == ["two"]


def test_reads_waiting_to_catch_up_are_not_batches_in_line(replicas: Replicas, kit: Any,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    # review: a read catching up took a place in the map's line that FUZZYRISK_MAX_PENDING_BATCHES counted:
    # reads waiting for another replica's batches made the replica refuse scan batches (503)
    a, b = replicas(max_pending_batches=2)
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert b.get("/maps/lab").status_code == 200
    assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 1)]}).status_code == 200  # b is one behind
    writes = b.app.state.service.writes  # type: ignore[attr-defined]
    catch_up, gate = writes._catch_up_locked, threading.Event()

    async def held_back(entry: Any, target: int) -> None:  # a catch-up that takes a while
        await asyncio.get_running_loop().run_in_executor(None, gate.wait, 10)
        await catch_up(entry, target)

    monkeypatch.setattr(writes, "_catch_up_locked", held_back)
    line = b.app.state.service.maps.entry("lab").line  # type: ignore[attr-defined]
    with ThreadPoolExecutor(3) as pool:
        reads = [pool.submit(b.get, "/maps/lab") for _ in range(2)]
        _wait_for(lambda: line.outstanding == 2)  # both reads in line, waiting to catch up
        batch = pool.submit(b.post, "/maps/lab/scans", json={"scans": [_scan(kit, 2)]})
        _wait_for(lambda: batch.done() or line.outstanding == 3)  # refused, or in line behind the reads
        gate.set()
        assert batch.result().status_code == 200, batch.result().text
        assert batch.result().json()["version"] == 2
        assert [read.result().status_code for read in reads] == [200, 200]
    assert kit.version(b, "lab") == kit.version(a, "lab") == 2


def _wait_for(condition: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def test_an_export_overtaken_by_another_replicas_snapshot_records_from_its_own_version(
        replicas: Replicas, kit: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    # review: the MCAP export read the log after the grid; a snapshot another replica wrote meanwhile gave a
    # recording whose scans start after a version newer than its grid (X-Scans-Since-Version > X-Map-Version)
    a, b = replicas(snapshot_every=3)
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 1)]}).status_code == 200
    assert kit.version(b, "lab") == 1  # b holds version 1
    storage = b.app.state.service.storage  # type: ignore[attr-defined]
    load_map, overtaken = storage.load_map, []

    def snapshot_meanwhile(name: str) -> Any:  # a writes 2 and 3 and snapshots at 3 as b copies its grid
        if not overtaken:
            overtaken.append(name)
            for k in (2, 3):
                assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, k)]}).status_code == 200
            kit.snapshots_stored(a)
        return load_map(name)

    monkeypatch.setattr(storage, "load_map", snapshot_meanwhile)
    exported = b.get("/maps/lab/export/mcap")
    assert exported.status_code == 200 and overtaken
    assert exported.headers["X-Map-Version"] == exported.headers["X-Scans-Since-Version"] == "3"
    assert kit.version(b, "lab") == 3


def test_a_map_no_replica_could_load_is_refused_at_creation(replicas: Replicas, kit: Any) -> None:
    # review: with a shared database POST /maps skipped FUZZYRISK_MAX_TOTAL_CELLS: a map larger than a replica's
    # memory was created (201), then every request for it answered 507 on every replica
    a, b = replicas(max_total_cells=5_000)
    bayes = {**kit.MAP_2D, "model": "bayes"}  # a bayes map holds its whole box from the start
    refused = a.post("/maps", json=bayes)  # 100 x 100 cells
    assert refused.status_code == 507 and "FUZZYRISK_MAX_TOTAL_CELLS" in error_message(refused)
    assert b.get("/maps").json() == [] and b.get("/maps/lab").status_code == 404
    assert a.post("/maps", json={**bayes, "resolution": 0.2}).status_code == 201  # 50 x 50 fits
    assert kit.version(b, "lab") == 0


def test_a_quarantine_ends_with_its_map_when_the_map_is_made_again(replicas: Replicas, kit: Any) -> None:
    # review: a replica kept its quarantine of a map deleted and made again elsewhere: the new map was served,
    # yet /ready went on reporting it quarantined
    a, b = replicas()
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 0)]}).status_code == 200
    with psycopg.connect(replicas.url, autocommit=True) as db:  # type: ignore[attr-defined]
        db.execute("UPDATE batches SET crc = crc + 1 WHERE map = 'lab'")  # a flipped bit
    assert b.get("/maps/lab").status_code == 503
    assert b.get("/ready").json()["maps_quarantined"] == ["lab"]
    assert a.delete("/maps/lab").status_code == 204
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    assert b.get("/maps/lab").json()["version"] == 0
    assert b.get("/ready").json()["maps_quarantined"] == []


def test_the_list_and_a_maps_own_route_agree_after_a_discarded_batch(
        replicas: Replicas, kit: Any, make_settings: Callable[..., Any], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    # review: after a batch discarded as a tombstone, GET /maps gave a map held by the replica the tombstone's
    # version and time, GET /maps/{name} the map's own
    _, b = replicas()
    settings = make_settings(data_dir=tmp_path / "c", database_url=replicas.url)  # type: ignore[attr-defined]
    with TestClient(create_app(settings), raise_server_exceptions=False) as a:  # a 500 is answered, not raised
        assert a.post("/maps", json=kit.MAP_2D).status_code == 201
        assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 0)]}).status_code == 200
        live = a.app.state.service.maps.entry("lab").map  # type: ignore[attr-defined]

        def out_of_memory(scans: Any, prepared: Any = None) -> Any:
            raise MemoryError("simulated")

        monkeypatch.setattr(live, "integrate_batch", out_of_memory)
        assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 1)]}).status_code == 500  # version 2: a tombstone
        for client in (a, b):
            got = client.get("/maps/lab").json()
            (listed,) = client.get("/maps").json()
            assert (listed["version"], listed["updated"]) == (got["version"], got["updated"])
            assert got["version"] == 1
        assert a.post("/maps/lab/scans", json={"scans": [_scan(kit, 2)]}).json()["version"] == 3
        for client in (a, b):
            got = client.get("/maps/lab").json()
            (listed,) = client.get("/maps").json()
            assert (listed["version"], listed["updated"], listed["scans_fused"]) == \
                (got["version"], got["updated"], got["scans_fused"])
            assert (got["version"], got["scans_fused"]) == (3, 2)


def test_a_map_imported_through_one_replica_is_served_and_scanned_through_the_other(replicas: Replicas,
                                                                                    kit: Any) -> None:
    from tests.app.formats.test_saved_maps import nav2_yaml, pgm, zipped

    a, b = replicas()
    grey = np.full((50, 60), 205, dtype=np.uint8)
    grey[5:45, 5:55] = 254
    grey[5, 5:55] = 0
    saved = zipped({"map.yaml": nav2_yaml(origin=[-3.0, -2.5, 0.0], resolution=0.1, free_thresh=0.196),
                    "map.pgm": pgm(grey)})
    zip_type = {"content-type": "application/zip"}
    made = a.post("/maps/import", params={"name": "floor"}, content=saved, headers=zip_type)
    assert made.status_code == 201, made.text
    assert made.json()["version"] == 1
    assert b.get("/maps/floor").json()["version"] == 1  # loaded by b from the database: its first batch replayed
    np.testing.assert_array_equal(kit.risk_npy(a, "floor"), kit.risk_npy(b, "floor"))
    assert b.post("/maps/floor/scans", json={"scans": [kit.laser(wall=1.0)]}).json()["version"] == 2
    assert kit.version(a, "floor") == 2
    np.testing.assert_array_equal(kit.risk_npy(a, "floor"), kit.risk_npy(b, "floor"))
    # the name is taken on every replica; a refused import makes nothing on any
    assert b.post("/maps/import", params={"name": "floor"}, content=saved, headers=zip_type).status_code == 409
    bad = b.post("/maps/import", params={"name": "other"}, content=zipped({"map.yaml": b"- not a map\n"}),
                 headers=zip_type)
    assert bad.status_code == 422
    assert [m["name"] for m in a.get("/maps").json()] == ["floor"]
