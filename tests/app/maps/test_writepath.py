"""The write path of a scan batch: group commit, commit pipelined with fusion, query checks, inline parsing.

What must hold whatever the timing: each batch of a map is committed and applied in arrival
order, a batch is on disk before its 200, readers never see part of a batch, and the map is
bit for bit an in-process fusion of the batches it acknowledged.
"""

from __future__ import annotations

import asyncio
import os
import io
import json
import sqlite3
import struct
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.maps import writepath
from app.storage.committer import GroupCommitter
from app.config import Settings
from app.api.factory import create_app
from app.ops.metrics import Metrics
from app.schemas import MapCreate, ScanBatch
from app.service.mapservice import MapService
from app.storage import BatchRecord, MapGone, SqliteStorage, StorageUnavailable
from fuzzyocc import FuzzyMap, GridSpec, LaserScan, SensorModel
from tests.conftest import error_message


def _rows(data_dir: Path) -> list[tuple[str, int]]:
    """The batch rows that hold a batch (a discarded one stays as an empty tombstone: its version stays taken)."""
    with sqlite3.connect(data_dir / "fuzzyrisk.sqlite3") as db:
        return db.execute("SELECT map, seq FROM batches WHERE length(payload) > 0 OR file IS NOT NULL "
                          "ORDER BY map, seq").fetchall()


def _bodies(kit: Any, n: int) -> list[dict[str, Any]]:
    return [{"scans": [kit.laser(x=0.1 * k, y=-0.2 * k, theta=0.3 * k, wall=2.05 + 0.1 * k)]} for k in range(n)]


def _replay(kit: Any, bodies: Sequence[dict[str, Any]]) -> bytes:
    """The risk of a fresh in-process map fed these batches one call each, in this order."""
    spec = kit.MAP_2D
    fresh = FuzzyMap(GridSpec(origin=spec["origin"], size=spec["size"], resolution=spec["resolution"]),
                     SensorModel(**spec["sensor"]))
    for body in bodies:
        batch = ScanBatch.model_validate(body)
        fresh.integrate_batch([
            LaserScan(pose=(s.pose.x, s.pose.y, s.pose.theta), angle_min=s.angle_min,  # type: ignore[union-attr]
                      angle_increment=s.angle_increment, ranges=np.array(s.ranges, dtype=np.float64),  # type: ignore[union-attr]
                      range_min=s.range_min, range_max=s.range_max)  # type: ignore[union-attr]
            for s in batch.scans
        ])
    return np.ascontiguousarray(fresh.risk()).tobytes()


class _SlowFusion:
    """Patches ``FuzzyMap.integrate_batch``: the first call on a map of the test's shape (``kit.MAP_2D``; the
    service's kernel warm-up fuses into small maps of its own as it starts) waits until ``release`` (and may fail)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, *, fail_first: bool = False) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        self.calls = 0
        original = FuzzyMap.integrate_batch

        def integrate(map_: FuzzyMap, scans: Any, prepared: Any = None) -> Any:
            if map_.spec.shape != (100, 100):
                return original(map_, scans, prepared)
            self.calls += 1
            if self.calls == 1:
                self.entered.set()
                assert self.release.wait(30)
                if fail_first:
                    raise MemoryError("simulated")
            return original(map_, scans, prepared)

        monkeypatch.setattr(FuzzyMap, "integrate_batch", integrate)


def _wait_for(condition: Any, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


# ---------------------------------------------------------------- group commit


class _RecordingStorage:
    """Storage stand-in: records each transaction; the first waits for ``gate``; ``bad`` names fail."""

    def __init__(self, bad: set[str] = frozenset()) -> None:  # type: ignore[assignment]
        self.transactions: list[list[BatchRecord]] = []
        self.gate = threading.Event()
        self.bad = bad

    def append_batches(self, batches: Sequence[BatchRecord]) -> list[int]:
        if not self.transactions:
            assert self.gate.wait(10)
        if any(b.name in self.bad for b in batches):
            raise StorageUnavailable("database or disk is full")
        self.transactions.append(list(batches))
        return [len(self.transactions)] * len(batches)


def test_batches_waiting_for_the_writer_share_one_transaction() -> None:
    storage = _RecordingStorage()
    committer = GroupCommitter(storage, Metrics())  # type: ignore[arg-type]
    first = committer.append(BatchRecord("a", None, b"1", "t", 1))
    time.sleep(0.05)  # the writer is now inside the first transaction, held at the gate
    waiting = [committer.append(BatchRecord(name, None, name.encode(), "t", 1)) for name in "bcd"]
    storage.gate.set()
    # each resolves to the version its store gave it (here: the number of its transaction)
    assert [future.result(timeout=10) for future in [first, *waiting]] == [1, 2, 2, 2]
    committer.shutdown()
    assert [[b.name for b in t] for t in storage.transactions] == [["a"], ["b", "c", "d"]]


def test_a_failed_group_is_retried_batch_by_batch_so_one_bad_batch_fails_alone() -> None:
    storage = _RecordingStorage(bad={"c"})
    committer = GroupCommitter(storage, Metrics())  # type: ignore[arg-type]
    first = committer.append(BatchRecord("a", None, b"1", "t", 1))
    time.sleep(0.05)
    waiting = {name: committer.append(BatchRecord(name, None, b"x", "t", 1)) for name in "bcd"}
    storage.gate.set()
    first.result(timeout=10)
    waiting["b"].result(timeout=10)
    waiting["d"].result(timeout=10)
    with pytest.raises(StorageUnavailable):
        waiting["c"].result(timeout=10)
    committer.shutdown()
    assert [[b.name for b in t] for t in storage.transactions] == [["a"], ["b"], ["d"]]


def test_a_group_commit_is_one_sqlite_transaction(tmp_path: Path) -> None:
    storage = SqliteStorage(tmp_path / "db.sqlite3")
    for name in ("m", "n"):
        storage.create_map(name, {"name": name}, "t0")
    assert storage.append_batches([BatchRecord("m", None, b"a", "t1", 1), BatchRecord("n", None, b"b", "t1", 1),
                                   BatchRecord("m", None, b"c", "t2", 1)]) == [1, 1, 2]
    with pytest.raises(MapGone):  # no map o: the whole group is refused
        storage.append_batches([BatchRecord("n", None, b"d", "t3", 1), BatchRecord("o", None, b"e", "t3", 1)])
    stored = {name: storage.load_map(name).batches for name in storage.map_names()}  # type: ignore[union-attr]
    storage.close()
    assert stored == {"m": [(1, b"a"), (2, b"c")], "n": [(1, b"b")]}


def test_concurrent_batches_to_several_maps_are_grouped_and_all_durable(make_client: Any, make_settings: Any,
                                                                         kit: Any) -> None:
    client = make_client()
    names = [f"m{i}" for i in range(4)]
    for name in names:
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    bodies = _bodies(kit, 6)

    def stream(name: str) -> list[int]:
        return [client.post(f"/maps/{name}/scans", json=body).json()["version"] for body in bodies]

    with ThreadPoolExecutor(len(names)) as pool:
        versions = list(pool.map(stream, names))
    assert versions == [list(range(1, len(bodies) + 1))] * len(names)
    assert _rows(make_settings().data_dir) == [(name, v) for name in names for v in range(1, len(bodies) + 1)]
    expected = _replay(kit, bodies)
    assert all(kit.risk_npy(client, name).tobytes() == expected for name in names)


# ---------------------------------------------------------------- commit pipelined with fusion


def test_the_next_batch_commits_while_the_previous_one_fuses(make_settings: Any, kit: Any,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    settings = make_settings()
    slow = _SlowFusion(monkeypatch)
    bodies = _bodies(kit, 3)
    with TestClient(create_app(settings)) as client, ThreadPoolExecutor(3) as pool:
        client.post("/maps", json=kit.MAP_2D)
        first = pool.submit(client.post, "/maps/lab/scans", json=bodies[0])
        assert slow.entered.wait(10)
        later = []
        for k, body in enumerate(bodies[1:], start=2):
            later.append(pool.submit(client.post, "/maps/lab/scans", json=body))
            # batch 1 is still fusing, and the next ones go on disk one after the other
            _wait_for(lambda k=k: _rows(settings.data_dir) == [("lab", v) for v in range(1, k + 1)])
        assert kit.version(client, "lab") == 0  # readers see none of them yet
        assert not first.done() and not any(f.done() for f in later)
        slow.release.set()
        assert [f.result().json()["version"] for f in [first, *later]] == [1, 2, 3]
        assert kit.risk_npy(client, "lab").tobytes() == _replay(kit, bodies)


def test_a_batch_failing_in_fusion_after_the_next_committed_leaves_a_version_gap_and_loses_nothing(
    make_settings: Any, kit: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = make_settings()
    slow = _SlowFusion(monkeypatch, fail_first=True)
    failing, following = _bodies(kit, 2)
    with TestClient(create_app(settings), raise_server_exceptions=False) as client, ThreadPoolExecutor(2) as pool:
        client.post("/maps", json=kit.MAP_2D)
        first = pool.submit(client.post, "/maps/lab/scans", json=failing)
        assert slow.entered.wait(10)
        second = pool.submit(client.post, "/maps/lab/scans", json=following)
        _wait_for(lambda: _rows(settings.data_dir) == [("lab", 1), ("lab", 2)])
        slow.release.set()
        assert first.result().status_code == 500
        assert second.result().json()["version"] == 2  # committed as 2 before batch 1 failed: it keeps it
        assert _rows(settings.data_dir) == [("lab", 2)]  # the failed batch is gone from the log
        risk = kit.risk_npy(client, "lab").tobytes()
        assert risk == _replay(kit, [following])
        assert client.post("/maps/lab/scans", json=following).json()["version"] == 3
    monkeypatch.undo()
    with TestClient(create_app(settings)) as again:  # the replay gives the same map
        assert kit.version(again, "lab") == 3
        assert kit.risk_npy(again, "lab").tobytes() == _replay(kit, [following, following])


def test_a_request_cancelled_after_parsing_is_still_committed_and_applied(
    tmp_path: Path, kit: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Cancelling the request (a client gone away) must not leave its batch on disk but not in the map."""
    slow = _SlowFusion(monkeypatch)
    body = _bodies(kit, 1)[0]

    async def scenario() -> tuple[int, int]:
        settings = Settings(data_dir=tmp_path / "data", plan_warmup=False, plan_workers=1)
        service = MapService(settings, SqliteStorage(settings.database_path), Metrics())
        await service.start()
        await service.maps.create_map(MapCreate(**kit.MAP_2D))
        request = asyncio.ensure_future(service.writes.add_scans(
            "lab", body=ScanBatch.model_validate(body).model_dump_json().encode(), content_type="application/json",
            query={},
        ))
        await asyncio.get_running_loop().run_in_executor(None, slow.entered.wait, 10)
        request.cancel()
        await asyncio.sleep(0.05)
        slow.release.set()
        with pytest.raises(asyncio.CancelledError):
            await request
        await service.stop()  # waits for the batch in flight, then snapshots it
        storage = SqliteStorage(settings.database_path)
        stored = storage.load_map("lab")
        storage.close()
        assert stored is not None
        return service.maps.entry("lab").version, stored.snapshot_version

    assert asyncio.run(scenario()) == (1, 1)


def test_readers_never_see_a_committed_batch_before_it_is_applied(make_settings: Any, kit: Any,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    slow = _SlowFusion(monkeypatch)
    with TestClient(create_app(make_settings())) as client, ThreadPoolExecutor(1) as pool:
        client.post("/maps", json=kit.MAP_2D)
        before = kit.risk_npy(client, "lab").tobytes()
        pending = pool.submit(client.post, "/maps/lab/scans", json=_bodies(kit, 1)[0])
        assert slow.entered.wait(10)
        info = client.get("/maps/lab").json()
        assert (info["version"], info["scans_fused"]) == (0, 0)
        slow.release.set()
        assert pending.result().json()["version"] == 1
        assert kit.risk_npy(client, "lab").tobytes() != before


# ---------------------------------------------------------------- the query and the parse


RAW_QUERY = {"x": 0, "y": 0, "theta": 0, "angle_min": -0.7, "angle_increment": 0.02, "range_min": 0.1,
             "range_max": 10}
RAW = {"content-type": "application/octet-stream"}


def _raw_ranges() -> bytes:
    return np.full(70, 2.5, dtype="<f4").tobytes()


@pytest.mark.parametrize(("value", "error"), [("nan", "finite_number"), ("-inf", "finite_number"),
                                              ("abc", "float_parsing"), ("", "float_parsing")])
def test_query_parameters_are_refused_as_fastapi_refuses_them(lab: TestClient, kit: Any, value: str,
                                                              error: str) -> None:
    response = lab.post("/maps/lab/scans", params={**RAW_QUERY, "theta": value}, content=_raw_ranges(), headers=RAW)
    assert response.status_code == 422
    body = response.json()
    assert body["code"] == "VALIDATION_ERROR" and body["message"].startswith("query.theta: ")
    assert body["details"] == [{"type": error, "loc": ["query", "theta"], "msg": body["details"][0]["msg"],
                                "input": value}]
    assert kit.version(lab, "lab") == 0


def test_the_query_is_checked_before_the_content_type_and_for_json_too(lab: TestClient, kit: Any) -> None:
    text = lab.post("/maps/lab/scans", params={"qx": "nan"}, content=b"x", headers={"content-type": "text/plain"})
    assert text.status_code == 422 and text.json()["details"][0]["loc"] == ["query", "qx"]
    assert lab.post("/maps/lab/scans", content=b"x", headers={"content-type": "text/plain"}).status_code == 415
    body = _bodies(kit, 1)[0]
    assert lab.post("/maps/lab/scans", params={"x": "inf"}, json=body).status_code == 422
    assert lab.post("/maps/lab/scans", params={"unknown": "nan"}, json=body).json()["version"] == 1


@pytest.mark.parametrize("headers", [{}, {"content-type": ""}])
def test_a_scan_upload_without_a_content_type_is_refused_and_changes_nothing(lab: TestClient, kit: Any,
                                                                             headers: dict) -> None:
    # what a web page's no-cors fetch sends, with no preflight: it must not reach the map
    body = json.dumps(_bodies(kit, 1)[0]).encode()
    response = lab.post("/maps/lab/scans", content=body, headers=headers)
    assert response.status_code == 415 and "needs a Content-Type" in error_message(response)
    assert kit.version(lab, "lab") == 0


def test_the_scan_query_is_documented_as_before(client: TestClient) -> None:
    params = client.get("/openapi.json").json()["paths"]["/maps/{name}/scans"]["post"]["parameters"]
    # point_step: raw binary points state their stride
    assert [p["name"] for p in params] == ["name", "x", "y", "z", "theta", "qx", "qy", "qz", "qw", "angle_min",
                                           "angle_increment", "range_min", "range_max", "registration_sigma",
                                           "point_step"]
    assert params[10] == {
        "name": "angle_increment", "in": "query", "required": False,
        "description": "binary uploads only; see the description",
        "schema": {"anyOf": [{"type": "number"}, {"type": "null"}], "title": "Angle Increment",
                   "description": "binary uploads only; see the description"},
    }


def test_bodies_parsed_on_the_loop_or_in_a_thread_fuse_the_same(make_client: Any, kit: Any,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    big = {"scans": [kit.laser(beams=4000, wall=2.0 + 0.1 * k) for k in range(4)]}
    small = _bodies(kit, 1)[0]
    assert len(ScanBatch.model_validate(big).model_dump_json()) > writepath.INLINE_PARSE_BYTES
    risks = []
    for inline_bytes in (writepath.INLINE_PARSE_BYTES, 0):  # default; then every body through a thread
        monkeypatch.setattr(writepath, "INLINE_PARSE_BYTES", inline_bytes)
        client = make_client()
        name = f"lab{inline_bytes}"
        client.post("/maps", json={**kit.MAP_2D, "name": name})
        assert client.post(f"/maps/{name}/scans", json=small).status_code == 200
        assert client.post(f"/maps/{name}/scans", json=big).status_code == 200
        assert client.post(f"/maps/{name}/scans", json={"scans": [{**kit.laser(), "angle_increment": 0}]}
                           ).status_code == 422
        assert client.post(f"/maps/{name}/scans", params=RAW_QUERY, content=_raw_ranges(), headers=RAW
                           ).json()["version"] == 3
        risks.append(kit.risk_npy(client, name).tobytes())
    assert risks[0] == risks[1]


# ---------------------------------------------------------------- the stored form of a batch


def _legacy_npz(scans: Sequence[Any]) -> bytes:
    """A batch as the service stored it before the framed format (``.npz``): old databases hold these."""
    arrays: dict[str, np.ndarray] = {"kinds": np.array(["laser" if isinstance(s, LaserScan) else "cloud" for s in scans])}
    for i, scan in enumerate(scans):
        if isinstance(scan, LaserScan):
            arrays[f"s{i}_scalars"] = np.array([*scan.pose, scan.angle_min, scan.angle_increment, scan.range_min,
                                                scan.range_max, scan.registration_sigma], dtype=np.float64)
            arrays[f"s{i}_values"] = scan.ranges.astype(np.float32)
        else:
            arrays[f"s{i}_scalars"] = np.array([*scan.origin, scan.range_max, scan.registration_sigma], dtype=np.float64)
            arrays[f"s{i}_values"] = scan.points
    out = io.BytesIO()
    np.savez(out, allow_pickle=False, **arrays)
    return out.getvalue()


def _mixed_scans() -> list[Any]:
    from fuzzyocc import PointCloud

    rng = np.random.default_rng(3)
    exact32 = rng.uniform(0.2, 9.0, 500).astype(np.float32).astype(np.float64)
    wide = rng.uniform(0.2, 9.0, 300)  # float64 values float32 cannot hold: kept as float64
    wide[[3, 7, 11]] = [np.nan, np.inf, -np.inf]
    exact32[[5, 9]] = [np.nan, np.inf]
    return [
        LaserScan(pose=(0.1, -0.2, 0.3), angle_min=-1.2, angle_increment=0.004, ranges=exact32, range_min=0.1,
                  range_max=8.0, registration_sigma=0.01),
        LaserScan(pose=(1.0 / 3.0, 0.0, -2.0), angle_min=-0.6, angle_increment=0.004, ranges=wide, range_min=0.05,
                  range_max=30.0),
        PointCloud(points=rng.uniform(-3, 3, (40, 2)), origin=(0.5, 0.25), range_max=6.0),
    ]


def _same_scans(a: Sequence[Any], b: Sequence[Any]) -> bool:
    for x, y in zip(a, b, strict=True):
        if type(x) is not type(y):
            return False
        if isinstance(x, LaserScan):
            def fields(s: LaserScan) -> tuple[Any, ...]:
                return (tuple(s.pose), s.angle_min, s.angle_increment, s.range_min, s.range_max, s.registration_sigma)

            if fields(x) != fields(y):
                return False
            if x.ranges.tobytes() != y.ranges.tobytes() or y.ranges.dtype != np.float64:
                return False
        else:
            if (tuple(x.origin), x.range_max, x.registration_sigma) != (tuple(y.origin), y.range_max, y.registration_sigma):
                return False
            if x.points.tobytes() != y.points.tobytes():
                return False
    return True


def test_a_stored_batch_decodes_to_the_same_scans_bit_for_bit() -> None:
    from app.maps import logcodec

    scans = _mixed_scans()
    payload = logcodec.encode(scans)
    assert payload.startswith(b"FRB\x01")
    assert _same_scans(scans, logcodec.decode(payload))
    assert len(payload) < 500 * 4 + 300 * 8 + 40 * 2 * 8 + 1000  # float32 where that loses nothing
    with pytest.raises(ValueError, match="after its last scan"):
        logcodec.decode(payload + b"\0")


def test_batches_stored_as_npz_by_earlier_versions_still_decode_and_replay(make_settings: Any, kit: Any) -> None:
    from app.maps import logcodec

    legacy = [_mixed_scans()[0], _mixed_scans()[2]]  # the old encoder stored laser ranges as float32
    assert _same_scans(legacy, logcodec.decode(_legacy_npz(legacy)))
    settings = make_settings()
    bodies = _bodies(kit, 3)
    with TestClient(create_app(settings)) as client:
        client.post("/maps", json=kit.MAP_2D)
    # the map's batches as an earlier version stored them: .npz payloads
    storage = SqliteStorage(settings.database_path)
    head = storage.map_head("lab")
    assert head is not None
    for body in bodies:
        old = [LaserScan(pose=(s["pose"]["x"], s["pose"]["y"], s["pose"]["theta"]), angle_min=s["angle_min"],
                         angle_increment=s["angle_increment"], ranges=np.array(s["ranges"], dtype=np.float64),
                         range_min=s["range_min"], range_max=s["range_max"]) for s in body["scans"]]
        storage.append_batches([BatchRecord("lab", head.incarnation, _legacy_npz(old), "2026-01-01T00:00:00.000+00:00",
                                            len(old))])
    storage.close()
    with TestClient(create_app(settings)) as again:
        assert kit.version(again, "lab") == 3
        assert kit.risk_npy(again, "lab").tobytes() == _replay(kit, bodies)
        assert again.post("/maps/lab/scans", json=bodies[0]).json()["version"] == 4  # new batches: new format
    # the graceful stop snapshotted all of them; they stay in the history
    assert _rows(settings.data_dir) == [("lab", version) for version in range(1, 5)]


def test_a_stored_batch_keeps_every_bit_of_odd_floats() -> None:
    from app.maps import logcodec

    ranges = np.array([1.5, -0.0, 5e-324, 1e300, np.inf, np.nan, np.nan])
    ranges.view(np.uint64)[6] = 0x7FF8000000000001  # a NaN with payload bits float32 cannot hold
    scan = LaserScan(pose=(0.0, 0.0, 0.0), angle_min=0.0, angle_increment=0.01, ranges=ranges, range_min=0.1,
                     range_max=8.0)
    (back,) = logcodec.decode(logcodec.encode([scan]))
    assert back.ranges.view(np.uint64).tolist() == ranges.view(np.uint64).tolist()


def test_a_corrupt_stored_batch_is_named_as_such_and_never_read_past_its_end() -> None:
    from app.maps import logcodec

    payload = logcodec.encode(_mixed_scans())
    for cut in range(len(payload)):  # truncated anywhere
        with pytest.raises(logcodec.CorruptBatch):
            logcodec.decode(payload[:cut])
    header_end = payload.index(b"]}") + 2
    for bad, good in [(b'"shape": [-1]', b'"shape": [500]'), (b'"scalars": -1', b'"scalars": 8'),
                      (b'"kind": "sonar"', b'"kind": "laser"')]:
        forged = payload[:header_end].replace(good, bad, 1)
        assert forged != payload[:header_end]
        length = len(forged) - len(payload[:8])
        forged = payload[:4] + struct.pack("<I", length) + forged[8:] + payload[header_end:]
        with pytest.raises(logcodec.CorruptBatch):
            logcodec.decode(forged)


def test_a_batch_whose_removal_from_the_log_fails_after_its_fusion_failed_does_not_block_the_next(
    make_settings: Any, kit: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = make_settings()
    failing, following = _bodies(kit, 2)
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        client.post("/maps", json=kit.MAP_2D)
        slow = _SlowFusion(monkeypatch, fail_first=True)
        slow.release.set()

        def refuse(self: SqliteStorage, name: str, version: int, incarnation: str | None = None) -> None:
            raise StorageUnavailable("disk I/O error")

        monkeypatch.setattr(SqliteStorage, "discard_batch", refuse)
        assert client.post("/maps/lab/scans", json=failing).status_code == 500
        assert _rows(settings.data_dir) == [("lab", 1)]  # still in the log: its version stays taken
        answer = client.post("/maps/lab/scans", json=following)
        assert answer.status_code == 200, answer.text
        assert answer.json()["version"] == 2
    monkeypatch.undo()
    # the graceful stop snapshotted the map as it was served, which supersedes the row left in the log
    with TestClient(create_app(settings)) as again:
        assert kit.version(again, "lab") == 2
        assert kit.risk_npy(again, "lab").tobytes() == _replay(kit, [following])
        assert again.post("/maps/lab/scans", json=following).json()["version"] == 3


def test_a_map_with_a_full_line_refuses_more_batches_with_503_and_other_maps_go_on(
    make_settings: Any, kit: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = make_settings(max_pending_batches=2)
    slow = _SlowFusion(monkeypatch)
    bodies = _bodies(kit, 3)
    with TestClient(create_app(settings)) as client, ThreadPoolExecutor(2) as pool:
        client.post("/maps", json=kit.MAP_2D)
        client.post("/maps", json={**kit.MAP_2D, "name": "other"})
        first = pool.submit(client.post, "/maps/lab/scans", json=bodies[0])
        assert slow.entered.wait(10)
        second = pool.submit(client.post, "/maps/lab/scans", json=bodies[1])
        _wait_for(lambda: _rows(settings.data_dir) == [("lab", 1), ("lab", 2)])
        refused = client.post("/maps/lab/scans", json=bodies[2])
        assert refused.status_code == 503 and refused.headers["Retry-After"] == "1"
        assert "FUZZYRISK_MAX_PENDING_BATCHES" in error_message(refused)
        assert _rows(settings.data_dir) == [("lab", 1), ("lab", 2)]  # nothing of it was stored
        # another map's line is its own
        assert client.post("/maps/other/scans", json=bodies[2]).json()["version"] == 1
        slow.release.set()
        assert [f.result().json()["version"] for f in (first, second)] == [1, 2]
        assert client.post("/maps/lab/scans", json=bodies[2]).json()["version"] == 3  # room again
        assert kit.risk_npy(client, "lab").tobytes() == _replay(kit, bodies)


def _hold_applies(service: Any, monkeypatch: pytest.MonkeyPatch, name: str) -> tuple[threading.Event, threading.Event]:
    """Hold every batch of map ``name`` in its fusion thread until ``release``; ``held`` is set when one is."""
    held, release = threading.Event(), threading.Event()
    apply = service.writes._apply

    def slow_apply(entry: Any, version: int, scans: Any, *rest: Any) -> Any:
        if entry.name == name:
            held.set()
            release.wait(60)
        return apply(entry, version, scans, *rest)

    monkeypatch.setattr(service.writes, "_apply", slow_apply)
    return held, release


def test_a_read_of_one_map_does_not_wait_behind_the_fusion_of_another(make_client: Any, kit: Any,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # every fusion thread busy with map a (held here, as a scan of millions of beams would be): a read
    # of map b is answered at once (a read of a third map waited 297 s behind two fusions)
    client = make_client(fusion_threads=1)
    for name in ("a", "b"):
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    service = client.app.state.service  # type: ignore[attr-defined]
    held, release = _hold_applies(service, monkeypatch, "a")
    with ThreadPoolExecutor(1) as pool:
        fusing = pool.submit(client.post, "/maps/a/scans", json={"scans": [kit.laser()]})
        assert held.wait(30)
        started = time.monotonic()
        for path in ("/maps/b/risk.npy", "/maps/b/risk.png", "/maps/b/occupancy_grid"):
            assert client.get(path).status_code == 200
        assert client.post("/maps/b/risk/query", json={"points": [[0.0, 0.0]]}).status_code == 200
        waited = time.monotonic() - started
        release.set()
        assert fusing.result(60).status_code == 200
    assert waited < 10.0  # before: until the fusion ended (here: never, release came after)


def test_a_read_of_a_map_does_not_wait_while_its_next_batch_is_cast(make_client: Any, kit: Any,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    # a lidar sweep's rays take most of its fusion: they are cast before the map is shut to readers
    monkeypatch.setattr(writepath, "CAST_AHEAD_CELLS", 0)  # a laser scan as a sweep is: cast ahead
    client = make_client()
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200
    before = kit.risk_npy(client, "lab")
    original, entered, release = FuzzyMap.prepare_batch, threading.Event(), threading.Event()

    def held(self: FuzzyMap, scans: Any) -> Any:
        if self.spec.shape == (100, 100):
            entered.set()
            assert release.wait(30)
        return original(self, scans)

    monkeypatch.setattr(FuzzyMap, "prepare_batch", held)
    with ThreadPoolExecutor(1) as pool:
        casting = pool.submit(client.post, "/maps/lab/scans", json={"scans": [kit.laser(x=1.0, wall=2.0)]})
        assert entered.wait(30)
        # answered while the batch is being cast: the map as it was, whole
        assert kit.version(client, "lab") == 1
        assert kit.risk_npy(client, "lab").tobytes() == before.tobytes()
        assert client.post("/maps/lab/risk/query", json={"points": [[0.0, 0.0]]}).status_code == 200
        release.set()
        assert casting.result(60).json()["version"] == 2
    assert kit.risk_npy(client, "lab").tobytes() == _replay(kit, [{"scans": [kit.laser()]},
                                                                  {"scans": [kit.laser(x=1.0, wall=2.0)]}])


def test_ready_shows_the_fusion_backlog_while_reads_are_served(make_client: Any, kit: Any,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    # two fusions of minutes stalled every map while /health stayed green and nothing said why
    client = make_client(fusion_threads=1)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    service = client.app.state.service  # type: ignore[attr-defined]
    held, release = _hold_applies(service, monkeypatch, "lab")
    with ThreadPoolExecutor(2) as pool:
        first = pool.submit(client.post, "/maps/lab/scans", json={"scans": [kit.laser()]})
        assert held.wait(30)
        second = pool.submit(client.post, "/maps/lab/scans", json={"scans": [kit.laser()]})
        deadline = time.monotonic() + 30
        while (ready := client.get("/ready").json())["batches_in_line"] < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        ready = client.get("/ready").json()
        assert ready["status"] == "ready" and ready["batches_in_line"] == 2 and ready["longest_fusion_job_s"] >= 0.3
        assert "fuzzyrisk_batches_in_line 2.0" in client.get("/metrics").text
        release.set()
        assert [f.result(60).json()["version"] for f in (first, second)] == [1, 2]
    ready = client.get("/ready").json()
    assert ready["batches_in_line"] == 0 and ready["longest_fusion_job_s"] == 0.0


def test_a_read_of_a_small_map_does_not_wait_behind_big_reads(make_client: Any, kit: Any,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    # bench abuse row 10: two readers of a 16 M-cell map's OccupancyGrid held both read threads, and
    # another map's reads waited (p99 13 -> 232 ms)
    from app.formats import exports
    from app.reads import service as reads

    client = make_client(read_threads=1)
    assert client.post("/maps", json={**kit.MAP_2D, "name": "big"}).status_code == 201  # 10,000 cells
    small = {**kit.MAP_2D, "name": "small", "size": [2.0, 2.0], "origin": [-1.0, -1.0]}  # 400 cells
    assert client.post("/maps", json=small).status_code == 201
    monkeypatch.setattr(reads, "HEAVY_READ_CELLS", 5_000)
    held, release = threading.Event(), threading.Event()
    npy_bytes = exports.npy_bytes

    def slow_npy(array: Any) -> bytes:
        if array.size == 10_000:
            held.set()
            release.wait(60)
        return npy_bytes(array)

    monkeypatch.setattr(exports, "npy_bytes", slow_npy)
    with ThreadPoolExecutor(1) as pool:
        big = pool.submit(client.get, "/maps/big/risk.npy")
        assert held.wait(30)  # the only heavy read thread is held
        started = time.monotonic()
        assert client.get("/maps/small/risk.npy").status_code == 200
        waited = time.monotonic() - started
        release.set()
        assert big.result(60).status_code == 200
    assert waited < 10.0  # before: until the big read ended (here: never, release came after)


def test_big_reads_take_turns_and_those_beyond_the_queue_are_refused(make_client: Any, kit: Any,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    # bench abuse row 10: big reads side by side each held a copy of the grid while they waited for
    # their render, and took both cores from the other clients; now one at a time, and a bounded queue
    from app.formats import exports
    from app.reads import service as reads

    client = make_client(heavy_read_queue=1, heavy_read_share=1.0)
    assert client.post("/maps", json={**kit.MAP_2D, "name": "big"}).status_code == 201  # 10,000 cells
    small = {**kit.MAP_2D, "name": "small", "size": [2.0, 2.0], "origin": [-1.0, -1.0]}  # 400 cells
    assert client.post("/maps", json=small).status_code == 201
    monkeypatch.setattr(reads, "HEAVY_READ_CELLS", 5_000)
    held, release = threading.Event(), threading.Event()
    rendered: list[int] = []
    npy_bytes = exports.npy_bytes

    def slow_npy(array: Any) -> bytes:
        if array.size == 10_000:
            rendered.append(array.size)
            held.set()
            release.wait(60)
        return npy_bytes(array)

    monkeypatch.setattr(exports, "npy_bytes", slow_npy)
    service = client.app.state.service  # type: ignore[attr-defined]
    with ThreadPoolExecutor(2) as pool:
        first = pool.submit(client.get, "/maps/big/risk.npy")
        assert held.wait(30)
        second = pool.submit(client.get, "/maps/big/occupancy_grid.cdr")
        deadline = time.monotonic() + 30
        while service.reads._lane.waiting < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        refused = client.get("/maps/big/risk", params={"format": "png"})
        assert refused.status_code == 503 and "FUZZYRISK_HEAVY_READ_QUEUE" in error_message(refused)
        assert refused.headers["Retry-After"] == "1"
        assert client.get("/maps/small/risk.npy").status_code == 200  # a small map's read is not in the lane
        assert rendered == [10_000] and not second.done()  # the second waits its turn, before its copy
        release.set()
        assert first.result(60).status_code == 200 and second.result(60).status_code == 200


def test_uploads_still_arriving_count_against_their_maps_line(make_client: Any, kit: Any) -> None:
    # bodies read side by side all passed a check that counted only batches already in line
    client = make_client(max_pending_batches=2)
    for name in ("lab", "other"):
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    service = client.app.state.service  # type: ignore[attr-defined]
    receiving = client.portal.wrap_async_context_manager  # type: ignore[union-attr]
    with receiving(service.writes.receiving("lab")), receiving(service.writes.receiving("lab")):  # two on their way
        refused = client.post("/maps/lab/scans", json={"scans": [kit.laser()]})
        assert refused.status_code == 503 and "arriving" in error_message(refused)
        assert refused.headers["Retry-After"] == "1"
        assert client.post("/maps/other/scans", json={"scans": [kit.laser()]}).status_code == 200  # its own line
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200  # room again
    assert kit.version(client, "lab") == 1 and service.maps.entry("lab").arriving == 0


def test_a_light_batch_is_not_held_behind_heavy_batches_of_other_maps(make_client: Any, kit: Any,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # two 2 M-beam scans held both fusion threads for 3-4 s; every other map's batch waited, and so
    # did the reads of those maps (behind their apply lock)
    client = make_client(fusion_threads=1)
    for name in ("heavy", "light"):
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
    monkeypatch.setattr(writepath, "HEAVY_BATCH_CELLS", 10_000)  # 900 beams of 3 m: about 27,000 cells
    original, entered, release = FuzzyMap.integrate_batch, threading.Event(), threading.Event()

    def held(self: FuzzyMap, scans: Any, prepared: Any = None) -> Any:
        if len(scans[0].ranges) == 900:
            entered.set()
            assert release.wait(30)
        return original(self, scans, prepared)

    monkeypatch.setattr(FuzzyMap, "integrate_batch", held)
    with ThreadPoolExecutor(1) as pool:
        heavy = pool.submit(client.post, "/maps/heavy/scans", json={"scans": [kit.laser(beams=900)]})
        assert entered.wait(30)  # the only fusion thread of its kind is held
        light = client.post("/maps/light/scans", json={"scans": [kit.laser(beams=90)]})  # about 2,700 cells
        assert light.status_code == 200 and light.json()["version"] == 1
        assert kit.version(client, "light") == 1
        assert not heavy.done()
        release.set()
        assert heavy.result().json()["version"] == 1


def test_heavy_batches_fuse_at_a_lower_priority_than_the_others() -> None:
    # measured (bench abuse row 6): at equal priority two 2 M-beam scans took two thirds of the cores from every
    # other map's fusion (the innocent's scan p99 4.1x its unloaded value); niced, 2.6x
    from app.ops.threads import Workers

    workers = Workers(fusion_threads=1, read_threads=1)

    def niceness() -> int:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    async def both() -> tuple[int, int]:
        return await workers.run_heavy(niceness), await workers.run(niceness)

    try:
        heavy, light = asyncio.run(both())
    finally:
        workers.shutdown()
    assert heavy > light
