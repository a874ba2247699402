"""A data directory that cannot take writes: 503 with nothing applied; a failed snapshot loses nothing."""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.errors import STORAGE_UNAVAILABLE_DETAIL
from app.maps.line import Turns
from app.storage import BatchRecord, SqliteStorage, StorageUnavailable


def _batch(kit: Any, k: int) -> dict[str, Any]:
    return {"scans": [kit.laser(x=0.1 * k, y=-0.2 * k, theta=0.3 * k, wall=2.05 + 0.1 * k)]}


def _fill_disk(client: TestClient) -> None:
    """Cap the database at its current size: the next write fails with SQLITE_FULL, as on a full disk."""
    db: sqlite3.Connection = client.app.state.service.storage._db  # type: ignore[attr-defined]
    pages = db.execute("PRAGMA page_count").fetchone()[0]
    db.execute(f"PRAGMA max_page_count = {pages}")


def _free_disk(client: TestClient) -> None:
    client.app.state.service.storage._db.execute("PRAGMA max_page_count = 1073741823")  # type: ignore[attr-defined]


def test_a_full_store_raises_storage_unavailable_and_stays_usable(tmp_path: Path) -> None:
    storage = SqliteStorage(tmp_path / "db.sqlite3")
    storage.create_map("m", {"name": "m"}, "t0")
    pages = storage._db.execute("PRAGMA page_count").fetchone()[0]
    storage._db.execute(f"PRAGMA max_page_count = {pages}")
    with pytest.raises(StorageUnavailable, match="full"):
        storage.append_batches([BatchRecord("m", None, b"\0" * 200_000, "t1", 1)])
    assert not storage._db.in_transaction  # rolled back: the next write can begin
    storage._db.execute("PRAGMA max_page_count = 1073741823")
    assert storage.append_batches([BatchRecord("m", None, b"\1" * 10, "t1", 1)]) == [1]
    assert storage.load_map("m").batches == [(1, b"\1" * 10)]  # type: ignore[union-attr]
    storage.close()


def test_a_full_disk_answers_503_json_and_applies_nothing(lab: TestClient, kit: Any) -> None:
    assert lab.post("/maps/lab/scans", json=_batch(kit, 0)).status_code == 200
    before = kit.risk_npy(lab, "lab")
    _fill_disk(lab)
    # larger than any free page, and small enough to go in its row (not in a payload file: see below)
    big = {"scans": [kit.laser(beams=10_000, wall=2.5 + 0.01 * k) for k in range(2)]}
    response = lab.post("/maps/lab/scans", json=big)
    assert response.status_code == 503, response.text
    assert response.json() == {"code": "STORAGE_UNAVAILABLE", "message": STORAGE_UNAVAILABLE_DETAIL, "details": None}
    assert int(response.headers["retry-after"]) > 0
    assert kit.version(lab, "lab") == 1 and np.array_equal(kit.risk_npy(lab, "lab"), before)
    _free_disk(lab)
    assert lab.post("/maps/lab/scans", json=big).json()["version"] == 2


def test_a_failed_snapshot_still_acknowledges_the_batch_and_loses_nothing(
    make_client: Any, kit: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refuse(*_args: Any) -> None:
        raise StorageUnavailable("database or disk is full")

    monkeypatch.setattr(SqliteStorage, "write_snapshot", refuse)
    client = make_client(snapshot_every=2)
    client.post("/maps", json=kit.MAP_2D)
    versions = [client.post("/maps/lab/scans", json=_batch(kit, k)).json()["version"] for k in range(5)]
    assert versions == [1, 2, 3, 4, 5]
    kit.snapshots_stored(client)
    metrics = client.get("/metrics").text
    assert "fuzzyrisk_snapshot_failures_total 2.0" in metrics  # at version 2, retried at 4 (not every batch)
    risk = kit.risk_npy(client, "lab")
    monkeypatch.undo()
    client.__exit__(None, None, None)  # the graceful stop's snapshot now succeeds
    again = make_client()
    assert kit.version(again, "lab") == 5
    assert kit.risk_npy(again, "lab").tobytes() == risk.tobytes()


def test_turns_pass_in_ticket_order_whatever_order_the_holders_get_ready() -> None:
    async def scenario() -> list[int]:
        turns, order = Turns(), []

        async def holder(ticket: int, ready_after: float, refused: bool = False) -> None:
            try:
                await asyncio.sleep(ready_after)  # parsing, which finishes in any order
                if refused:
                    return  # gives its turn up without waiting for it
                await turns.wait(ticket)
                order.append(ticket)
                await asyncio.sleep(0.001)
            finally:
                turns.done(ticket)

        tickets = [turns.take() for _ in range(5)]
        delays = [0.03, 0.0, 0.02, 0.01, 0.0]
        tasks = [asyncio.create_task(holder(t, d, refused=(t == 2))) for t, d in zip(tickets, delays)]
        stuck = asyncio.create_task(holder(turns.take(), 10.0))  # cancelled below: must not block ticket 6
        last = asyncio.create_task(holder(turns.take(), 0.0))
        await asyncio.gather(*tasks)
        stuck.cancel()
        await asyncio.wait_for(last, timeout=2.0)
        return order

    assert asyncio.run(scenario()) == [0, 1, 3, 4, 6]
