"""The history kept: snapshots keep the batches they cover, ``FUZZYRISK_MAX_HISTORY_BYTES`` folds the oldest into a
base snapshot, and the map rebuilt from the base and the history is the live map bit for bit; SQLite and PostgreSQL."""

from __future__ import annotations

import shutil
import sqlite3
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.factory import create_app
from app.config import Settings
from app.maps.history import FOLD_DOWN_TO, rebuild
from app.storage import SqliteStorage, Storage
from fuzzyocc import FuzzyMap, GridSpec, LaserScan, SensorModel

MakeClient = Callable[..., TestClient]


@pytest.fixture(params=["sqlite", "postgres"])
def on(request: pytest.FixtureRequest) -> dict[str, Any]:
    """Settings of a service on each store: SQLite in its data directory, then a new PostgreSQL database."""
    if request.param == "sqlite":
        return {}
    return {"database_url": request.getfixturevalue("postgres_server").create_database()}


def _body(kit: Any, k: int) -> dict[str, Any]:
    """One scan, a different view of the lab for each ``k`` (the same number of beams: the same bytes stored)."""
    return {"scans": [kit.laser(x=0.1 * (k % 7), y=-0.1 * (k % 5), theta=0.2 * k, wall=2.5 + 0.05 * k)]}


def _post(client: TestClient, kit: Any, ks: range) -> None:
    for k in ks:
        assert client.post("/maps/lab/scans", json=_body(kit, k)).status_code == 200
        kit.snapshots_stored(client)  # and the fold after a snapshot, when one was due


def _batch_bytes(make_client: MakeClient, kit: Any, tmp_path: Path) -> int:
    """What one batch of ``_body`` takes in the history, as a service of its own says."""
    probe = make_client(data_dir=tmp_path / "probe")
    probe.post("/maps", json=kit.MAP_2D)
    _post(probe, kit, range(1))
    return int(probe.get("/maps/lab").json()["history"]["bytes"])


def _storage(client: TestClient) -> Storage:
    return client.app.state.service.storage  # type: ignore[attr-defined, no-any-return]


def _live_arrays(client: TestClient) -> tuple[bytes, bytes]:
    live = client.app.state.service.maps.entry("lab").map  # type: ignore[attr-defined]
    return live.risk().tobytes(), live.observed().tobytes()


def _rebuilt_arrays(storage: Storage) -> tuple[bytes, bytes]:
    history = storage.load_history("lab")
    assert history is not None and history.damage == []
    rebuilt = rebuild(history).map
    return rebuilt.risk().tobytes(), rebuilt.observed().tobytes()


def _fused_from_scratch(kit: Any, ks: range) -> tuple[bytes, bytes]:
    """The lab fused in-process from nothing with the scans ``ks`` (no service, no store)."""
    fused = FuzzyMap(GridSpec(origin=tuple(kit.MAP_2D["origin"]), size=tuple(kit.MAP_2D["size"]),
                              resolution=kit.MAP_2D["resolution"]), SensorModel(range_sigma=0.03))
    for k in ks:
        s = _body(kit, k)["scans"][0]
        fused.integrate_batch([LaserScan(pose=(s["pose"]["x"], s["pose"]["y"], s["pose"]["theta"]),
                                         angle_min=s["angle_min"], angle_increment=s["angle_increment"],
                                         ranges=np.array(s["ranges"], dtype=float), range_min=s["range_min"],
                                         range_max=s["range_max"])])
    return fused.risk().tobytes(), fused.observed().tobytes()


def test_while_nothing_left_the_history_a_rebuild_is_the_map_fused_from_scratch(make_client: MakeClient, kit: Any,
                                                                                on: dict[str, Any]) -> None:
    client = make_client(snapshot_every=3, **on)
    client.post("/maps", json=kit.MAP_2D)
    _post(client, kit, range(1, 9))  # snapshots at 3 and 6 keep the batches they cover
    assert client.get("/maps/lab").json()["history"]["from_version"] == 0
    assert client.get("/maps/lab").json()["history"]["scans"] == 8
    history = _storage(client).load_history("lab")
    assert history is not None and history.snapshot is None  # from the map's creation
    assert [version for version, _ in history.batches] == list(range(1, 9))
    assert _rebuilt_arrays(_storage(client)) == _live_arrays(client) == _fused_from_scratch(kit, range(1, 9))


def test_the_budget_folds_the_oldest_batches_into_a_base_and_a_restart_serves_the_same_map(
        make_client: MakeClient, kit: Any, on: dict[str, Any], tmp_path: Path) -> None:
    size = _batch_bytes(make_client, kit, tmp_path)
    budget = 4 * size + size // 2
    settings = {"snapshot_every": 2, "max_history_bytes": budget, **on}
    client = make_client(**settings)
    client.post("/maps", json=kit.MAP_2D)
    folded_at = []
    for k in range(1, 11):
        _post(client, kit, range(k, k + 1))
        history = client.get("/maps/lab").json()["history"]
        assert history["bytes"] == history["scans"] * size  # one scan a batch, every batch the same bytes
        if history["from_version"] not in folded_at[-1:]:
            folded_at.append(history["from_version"])
            # over the budget at a snapshot: folded down to about 3/4 of it, the batches after the base kept
            assert history["bytes"] <= budget * FOLD_DOWN_TO and history["scans"] == k - history["from_version"]
    assert folded_at[0] == 0 and len(folded_at) > 2  # folded more than once, each time from a newer base
    info = client.get("/maps/lab").json()
    assert info["version"] == 10 and info["scans_fused"] == 10 and 0 < info["history"]["from_version"] < 10
    # the base plus the history is the live map, and the map fused from scratch: the base is that map at its version
    assert _rebuilt_arrays(_storage(client)) == _live_arrays(client) == _fused_from_scratch(kit, range(1, 11))
    risk = kit.risk_npy(client, "lab")
    client.__exit__(None, None, None)

    again = make_client(**settings)
    assert again.get("/maps/lab").json() == info
    assert kit.risk_npy(again, "lab").tobytes() == risk.tobytes()
    _post(again, kit, range(11, 13))  # and it goes on from there
    assert _rebuilt_arrays(_storage(again)) == _live_arrays(again) == _fused_from_scratch(kit, range(1, 13))


def test_a_budget_of_zero_keeps_no_history_beyond_what_a_restart_needs(make_client: MakeClient, kit: Any,
                                                                       on: dict[str, Any]) -> None:
    client = make_client(snapshot_every=2, max_history_bytes=0, **on)
    client.post("/maps", json=kit.MAP_2D)
    _post(client, kit, range(1, 6))
    history = client.get("/maps/lab").json()["history"]
    # the snapshot at 4 is the base: only batch 5, which a restart replays, is stored
    assert (history["from_version"], history["scans"]) == (4, 1)
    assert _rebuilt_arrays(_storage(client)) == _live_arrays(client)


def test_a_kill_during_a_fold_leaves_the_map_at_its_acknowledged_version(make_client: MakeClient,
                                                                         make_settings: Callable[..., Settings],
                                                                         kit: Any, tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    size = _batch_bytes(make_client, kit, tmp_path)
    # the fold's transaction, all its statements run, waits before its COMMIT: a kill -9 there is a copy
    # of the data directory then (SQLite recovers the database as it was before the transaction)
    inside, release = threading.Event(), threading.Event()
    transaction = SqliteStorage._transaction

    def held(self: SqliteStorage, work: Callable[..., Any]) -> Any:
        def then_wait(db: sqlite3.Connection) -> Any:
            result = work(db)
            if work.__name__ == "fold":
                inside.set()
                assert release.wait(30)
            return result

        return transaction(self, then_wait)

    monkeypatch.setattr(SqliteStorage, "_transaction", held)
    settings = make_settings(snapshot_every=2, max_history_bytes=2 * size + size // 2)
    client = make_client(snapshot_every=2, max_history_bytes=2 * size + size // 2)
    client.post("/maps", json=kit.MAP_2D)
    _post(client, kit, range(1, 4))  # the snapshot at 2 stored (a new one is not started while one is written)
    # the snapshot at 4 finds 4 batches over the budget: batches 1-3 are folded
    assert client.post("/maps/lab/scans", json=_body(kit, 4)).status_code == 200
    try:
        assert inside.wait(30)
        killed = tmp_path / "killed"
        shutil.copytree(settings.data_dir, killed)
    finally:
        release.set()
    kit.snapshots_stored(client)
    folded = client.get("/maps/lab").json()
    assert (folded["version"], folded["history"]["from_version"]) == (4, 3)
    # the history starts at the first scan it still holds: batch 4's (stamped when the service received it)
    assert folded["history"]["from_stamp"] == client.get("/maps/lab/trajectory").json()["poses"][0]["header"]["stamp"]
    risk = kit.risk_npy(client, "lab")
    monkeypatch.undo()

    with TestClient(create_app(Settings(data_dir=killed, plan_warmup=False))) as restarted:
        info = restarted.get("/maps/lab").json()
        first = restarted.get("/maps/lab/trajectory").json()["poses"][0]["header"]["stamp"]
        assert info["version"] == 4 and info["history"] == {"from_version": 0, "from_stamp": first, "bytes": 4 * size,
                                                            "scans": 4}
        assert kit.risk_npy(restarted, "lab").tobytes() == risk.tobytes()
        assert _rebuilt_arrays(_storage(restarted)) == _live_arrays(restarted)
    client.__exit__(None, None, None)
    with TestClient(create_app(settings)) as after:  # and once the fold committed: the new history
        assert after.get("/maps/lab").json()["history"] == folded["history"]
        assert kit.risk_npy(after, "lab").tobytes() == risk.tobytes()
        assert _rebuilt_arrays(_storage(after)) == _live_arrays(after)


def test_two_replicas_sharing_a_map_see_one_fold_and_serve_the_same_map(make_client: MakeClient, kit: Any,
                                                                         postgres_server: Any, tmp_path: Path) -> None:
    size = _batch_bytes(make_client, kit, tmp_path)
    url = postgres_server.create_database()
    settings = {"snapshot_every": 2, "max_history_bytes": 4 * size + size // 2, "database_url": url}
    a = make_client(data_dir=tmp_path / "a", **settings)
    b = make_client(data_dir=tmp_path / "b", **settings)
    assert a.post("/maps", json=kit.MAP_2D).status_code == 201
    _post(b, kit, range(1, 2))  # b holds version 1, then falls behind
    for k in range(2, 11):  # both write; a's snapshots fold the history
        _post(a if k % 3 else b, kit, range(k, k + 1))
    _post(a, kit, range(11, 13))
    seen_by_a, seen_by_b = a.get("/maps/lab").json(), b.get("/maps/lab").json()
    assert seen_by_a == seen_by_b and seen_by_a["version"] == 12 and seen_by_a["history"]["from_version"] > 0
    assert kit.risk_npy(a, "lab").tobytes() == kit.risk_npy(b, "lab").tobytes()
    # the history (its base, written by whichever replica folded first, and the batches after it) rebuilds the map
    # both serve
    assert _rebuilt_arrays(_storage(a)) == _live_arrays(a) == _live_arrays(b) == _fused_from_scratch(kit, range(1, 13))
    c = make_client(data_dir=tmp_path / "c", **settings)  # a replica that loads the map after the folds
    assert c.get("/maps/lab").json() == seen_by_a
    assert kit.risk_npy(c, "lab").tobytes() == kit.risk_npy(a, "lab").tobytes()


def test_replicas_folding_the_same_history_fold_it_once(postgres_server: Any) -> None:
    from app.storage import BatchRecord
    from app.storage.postgres import PostgresStorage

    url = postgres_server.create_database()
    first, second = PostgresStorage(url), PostgresStorage(url)
    try:
        first.create_map("m", {"name": "m", "incarnation": "i"}, "t0")
        for k in range(1, 5):
            first.append_batches([BatchRecord("m", "i", bytes([k]) * 10, f"t{k}", 1)])
        first.write_snapshot("m", 4, b"four")
        assert first.fold_point("m", 15) == second.fold_point("m", 15) == 3
        assert first.write_base("m", 3, b"three", "i")
        assert not second.write_base("m", 3, b"another three", "i")  # found it done
        assert not second.write_base("m", 2, b"two", "i")  # nor goes back
        history = second.load_history("m")
        assert history is not None and (history.snapshot_version, history.snapshot) == (3, b"three")
        assert history.batches == [(4, bytes([4]) * 10)] and history.damage == []
        head = second.map_head("m")
        assert head is not None and (head.base_version, head.history_bytes, head.history_scans) == (3, 10, 1)
        assert not second.write_base("m", 5, None, "i")  # never past the restart snapshot
    finally:
        first.close()
        second.close()
