"""kill -9 while several robots stream at once, so that batches are made durable in shared transactions
(group commit): every acknowledged batch survives, every map loads whole, and each map is bit for bit an
in-process fusion of the batches it holds."""

from __future__ import annotations

import http.client
import random
import threading
import time

import httpx
import numpy as np
import pytest

from bench._client import Batch, Fleet, LeanClient, ServerProcess, new_map, npy_array

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

ROBOTS = 4
GROUP_BUCKET = 'fuzzyrisk_batch_commit_group_size_bucket{le="1.0"}'
GROUP_COUNT = "fuzzyrisk_batch_commit_group_size_count"


def _groups(client: httpx.Client) -> tuple[float, float]:
    """(transactions of one batch, all transactions) so far, from /metrics."""
    values = {}
    for line in client.get("/metrics").text.splitlines():
        key, _, value = line.rpartition(" ")
        if key in (GROUP_BUCKET, GROUP_COUNT):
            values[key] = float(value)
    return values.get(GROUP_BUCKET, 0.0), values.get(GROUP_COUNT, 0.0)


def _robot_batches(fleet: Fleet, r: int) -> list[Batch]:
    # even robots JSON batches of 2 scans, odd robots binary single scans, as in the load bench
    return fleet.batches(r, 2, binary=False) if r % 2 == 0 else fleet.batches(r, 1, binary=True)


@pytest.mark.parametrize("seed", [3, 4])
def test_acknowledged_batches_of_a_shared_transaction_survive_kill_9(seed: int) -> None:
    rng = random.Random(seed)
    fleet = Fleet.generate(ROBOTS, 40, seed=seed)
    names = [f"robot-{r}" for r in range(ROBOTS)]
    batches = {name: _robot_batches(fleet, r) for r, name in enumerate(names)}
    acked: dict[str, list[int]] = {name: [] for name in names}
    server = ServerProcess(env={"FUZZYRISK_SNAPSHOT_EVERY": "7"})  # snapshots land among the kills too
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=30.0) as client:
            for name in names:
                client.post("/maps", json=fleet.map_request(name)).raise_for_status()

        def stream(name: str) -> None:
            with LeanClient(server.url, timeout=30.0) as lean:
                for batch in batches[name]:
                    try:
                        status = lean.post(name, batch)
                    except (OSError, http.client.HTTPException):
                        return  # killed under us
                    if status != 200:
                        return
                    acked[name].append(len(acked[name]) + 1)

        threads = [threading.Thread(target=stream, args=(name,)) for name in names]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 60
        with httpx.Client(base_url=server.url, timeout=30.0) as client:
            while True:
                single, total = _groups(client)
                if total - single >= 2 and min(len(a) for a in acked.values()) >= 4:
                    break  # transactions of several batches happened, and every robot is streaming
                assert time.monotonic() < deadline, f"no group commit seen: {single} of {total} alone"
                assert all(t.is_alive() for t in threads), "a stream ended before the kill"
                time.sleep(0.01)
        time.sleep(rng.uniform(0.0, 0.05))
        server.kill()
        for t in threads:
            t.join(timeout=30)
        last = {name: len(acked[name]) for name in names}
        assert all(last[name] < len(batches[name]) for name in names), "the kill must land mid-stream"

        server.start()
        with httpx.Client(base_url=server.url, timeout=30.0) as client:
            for name in names:
                info = client.get(f"/maps/{name}").json()
                version = int(info["version"])
                # every acknowledged batch is there; the one in flight wholly or not at all
                assert last[name] <= version <= last[name] + 1, (name, last[name], version)
                replay = new_map(fleet.spec)
                for batch in batches[name][:version]:
                    replay.integrate_batch(batch.laser_scans())
                assert int(info["scans_fused"]) == replay.scans_fused
                held = npy_array(client.get(f"/maps/{name}/risk", params={"format": "npy"}))
                assert np.array_equal(held, replay.risk()), name
    finally:
        server.close()
