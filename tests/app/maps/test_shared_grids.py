"""Map grids shared with the planner workers (``app.maps.shared_grids``): a plan runs on the version it reports,
the files go with their version, their map and the service, stay within FUZZYRISK_PLAN_CACHE_BYTES, and a
replaced worker plans on them again."""

from __future__ import annotations

import multiprocessing.forkserver
import re
import signal
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
from fastapi.testclient import TestClient

GOAL = [2.0, 0.3]  # where the second scan puts a wall


def _plan(client: TestClient, name: str = "lab", **body: Any) -> Any:
    request = {"start": [0.5, 0.0], "goal": GOAL, "planner": "grid", **body}
    return client.post(f"/maps/{name}/plan", json=request)


def _files(client: TestClient) -> list[str]:
    """The grids' files of the service's run (names ``m<map>-v<version>.<array>.npy``)."""
    root = client.app.state.settings.data_dir / "plan-grids"
    return sorted(p.name for p in root.glob("*/*.npy"))


def _bytes_on_disk(client: TestClient) -> int:
    root = client.app.state.settings.data_dir / "plan-grids"
    return sum(p.stat().st_size for p in root.glob("*/*.npy"))


def _sources(client: TestClient) -> dict[str, float]:
    text = client.get("/metrics").text
    return {m[1]: float(m[2]) for m in re.finditer(r'^fuzzyrisk_plan_grids_total\{source="(\w+)"\} (\S+)$', text, re.M)}


def _versions(files: list[str]) -> set[int]:
    return {int(re.match(r"m\d+-v(\d+)\.", f)[1]) for f in files}  # type: ignore[index]


def test_a_plan_after_a_scan_runs_on_the_new_version(lab: TestClient, kit: Any) -> None:
    assert lab.post("/maps/lab/scans", json={"scans": [kit.laser(wall=3.0)]}).status_code == 200
    first, again = _plan(lab), _plan(lab)
    assert first.status_code == again.status_code == 200, first.text
    assert first.json()["version"] == again.json()["version"] == 1
    assert first.json()["path"] == again.json()["path"]
    assert _sources(lab) == {"published": 1.0, "shared": 1.0}  # the second plan used the grid the first published
    assert _versions(_files(lab)) == {1}

    # a wall where the goal is, seen three times: the published grid of version 1 must not be planned on
    assert lab.post("/maps/lab/scans", json={"scans": [kit.laser(wall=2.0)] * 3}).status_code == 200
    assert _files(lab) == []  # version 1's files went as version 2 was applied
    blocked = _plan(lab)
    assert blocked.status_code == 422 and blocked.json()["code"] == "GOAL_OCCUPIED", blocked.text
    short = _plan(lab, goal=[1.0, 0.3])
    assert short.status_code == 200 and short.json()["version"] == 2
    assert _versions(_files(lab)) == {2}
    assert _sources(lab)["shared"] == 2.0  # the refused plan published version 2, the next one shared it


def test_the_grids_of_a_deleted_map_and_of_a_stopped_service_are_gone(make_client: Any, kit: Any) -> None:
    client = make_client()
    files = {}
    for name in ("lab", "other"):
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
        assert client.post(f"/maps/{name}/scans", json={"scans": [kit.laser()]}).status_code == 200
        before = set(_files(client))
        assert _plan(client, name).status_code == 200
        files[name] = set(_files(client)) - before
        assert len(files[name]) == 2  # its risk and observed mask
    assert client.delete("/maps/lab").status_code == 204
    assert set(_files(client)) == files["other"]
    # a new map of the same name is not served the old map's grid
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser(wall=2.0)] * 3}).status_code == 200
    assert _plan(client).json()["code"] == "GOAL_OCCUPIED"
    root = client.app.state.settings.data_dir / "plan-grids"
    client.__exit__(None, None, None)
    assert not root.exists()  # nothing of the run is left


def test_a_killed_services_grids_are_removed_at_the_next_start(make_settings: Any, make_client: Any) -> None:
    root = make_settings().data_dir / "plan-grids"
    left = root / "12345-deadbeef"  # what a kill -9 leaves: a run directory whose lock nobody holds
    left.mkdir(parents=True)
    (left / "lock").touch()
    (left / "m1-v3.risk.npy").write_bytes(b"\0" * 1000)
    make_client()
    assert not left.exists()


@pytest.mark.parametrize("bound", [0, 80_000, 200_000])
def test_the_grids_stay_within_their_byte_bound(make_client: Any, kit: Any, bound: int) -> None:
    # a grid of lab is 100 x 100 cells: 40 kB of risk and 10 kB of observed mask (and the headers)
    client = make_client(plan_cache_bytes=bound)
    names = ["a", "b", "c"]
    for name in names:
        assert client.post("/maps", json={**kit.MAP_2D, "name": name}).status_code == 201
        assert client.post(f"/maps/{name}/scans", json={"scans": [kit.laser()]}).status_code == 200
    for name in names * 2:
        response = _plan(client, name)
        assert response.status_code == 200 and response.json()["status"] == "exact", response.text
        assert _bytes_on_disk(client) <= bound
        gauge = re.search(r"^fuzzyrisk_plan_grid_bytes (\S+)$", client.get("/metrics").text, re.M)
        assert gauge is not None and float(gauge[1]) <= bound
    sources = _sources(client)
    if bound == 0:  # off: every plan ships its grid, no file is written
        assert sources == {"shipped": 6.0} and _files(client) == []
    elif bound == 80_000:  # one grid fits: each map's grid pushes the previous one out
        assert sources == {"published": 6.0} and len(_files(client)) == 2
    else:  # all three fit: the second round shares them
        assert sources == {"published": 3.0, "shared": 3.0} and len(_files(client)) == 6


def test_a_grid_larger_than_the_bound_is_shipped_with_its_plan(make_client: Any, kit: Any) -> None:
    client = make_client(plan_cache_bytes=20_000)
    assert client.post("/maps", json=kit.MAP_2D).status_code == 201
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200
    assert _plan(client).status_code == 200
    assert _sources(client) == {"shipped": 1.0} and _files(client) == []


def _workers() -> list[psutil.Process]:
    """The planner workers: children of this process's forkserver (only this test's pool has any)."""
    pid = getattr(multiprocessing.forkserver._forkserver, "_forkserver_pid", None)
    assert pid is not None
    return [p for p in psutil.Process(pid).children() if p.status() != psutil.STATUS_ZOMBIE]


def test_a_replaced_worker_plans_on_the_published_grid(lab: TestClient, kit: Any) -> None:
    assert lab.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200
    before = _plan(lab)
    assert before.status_code == 200
    (worker,) = _workers()
    worker.send_signal(signal.SIGKILL)  # as the OOM killer would, while it waits for work
    worker.wait(10)
    statuses = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        response = _plan(lab)
        statuses.append(response.status_code)
        if response.status_code == 200:
            break
        assert response.status_code == 503, response.text  # the plan that found the worker gone, at most
    assert statuses[-1] == 200 and len(statuses) <= 2, statuses
    assert response.json()["path"] == before.json()["path"] and response.json()["version"] == 1
    (replacement,) = _workers()
    assert replacement.pid != worker.pid
    assert _sources(lab)["shared"] >= 1.0  # the new worker read the published grid


def test_a_worker_keeps_a_grids_field_and_its_dilations_for_the_next_plans(tmp_path: Path) -> None:
    import asyncio

    import numpy as np

    from app.maps.shared_grids import PlanGrids
    from app.plans.pool import PlanPool
    from app.plans.worker import run_shared_plan, worker_fields

    risk = np.full((60, 40), 0.1, np.float32)
    risk[30, :30] = 1.0
    observed = np.ones(risk.shape, bool)
    params = {"start": [0.5, 0.5], "goal": [2.5, 0.5], "planner": "grid", "robot_radius": 0.1}

    async def scenario() -> tuple[list[dict[str, Any]], list[str]]:
        loop = asyncio.get_running_loop()
        grids = PlanGrids(tmp_path / "plan-grids", 10**6, lambda fn, *a: loop.run_in_executor(None, fn, *a))
        grids.open()
        pool = PlanPool(workers=1, queue=1, field_cache_bytes=10**6)
        try:
            lease = await grids.publish(7, 1, risk, observed, 0.05, (0.0, 0.0), current=lambda: True)
            assert lease is not None
            seen, paths = [], []
            for radius in (0.1, 0.1, 0.2):
                answer = await pool.run(run_shared_plan, 30.0, lease.ref, {**params, "robot_radius": radius})
                paths.append(answer["result"]["status"])
                seen.append(await pool.run(worker_fields, 30.0))
            lease.release()
            grids.retire(7)  # the map is gone: its files go, and the worker forgets the field at its next plan
            newer = await grids.publish(7, 2, risk, observed, 0.05, (0.0, 0.0), current=lambda: True)
            assert newer is not None
            await pool.run(run_shared_plan, 30.0, newer.ref, params)
            seen.append(await pool.run(worker_fields, 30.0))
            newer.release()
            return seen, paths
        finally:
            pool.shutdown()
            grids.close()

    seen, statuses = asyncio.run(scenario())
    assert statuses == ["exact"] * 3
    assert [s["loads"] for s in seen] == [1, 1, 1, 2]  # read from its files once per version
    base = risk.nbytes + observed.nbytes
    per_radius = 2 * risk.nbytes  # the dilated risk, and the dilated risk of the observed cells
    assert [s["bytes"] for s in seen[:3]] == [base + per_radius, base + per_radius, base + 2 * per_radius]
    assert len(seen[3]["paths"]) == 1 and seen[3]["paths"][0].endswith("m7-v2.risk.npy")
    assert not (tmp_path / "plan-grids").exists()


def test_first_plans_of_a_version_share_one_write_and_a_cancelled_one_leaves_no_file(tmp_path: Path) -> None:
    import asyncio
    import threading

    import numpy as np

    from app.maps.shared_grids import PlanGrids

    risk, observed = np.zeros((50, 50), np.float32), np.ones((50, 50), bool)
    gate, writes = threading.Event(), []

    async def scenario() -> None:
        loop = asyncio.get_running_loop()

        def slow(fn: Any, *args: Any) -> Any:
            def run() -> Any:
                writes.append(args[0].risk_path)
                gate.wait(10)
                return fn(*args)

            return loop.run_in_executor(None, run)

        grids = PlanGrids(tmp_path / "plan-grids", 10**6, slow)
        grids.open()
        try:
            # two first plans of version 1: one write, both hold the grid
            publish = [asyncio.ensure_future(grids.publish(1, 1, risk, observed, 0.1, (0.0, 0.0), lambda: True))
                       for _ in range(2)]
            await asyncio.sleep(0.05)
            gate.set()
            leases = await asyncio.gather(*publish)
            assert len(writes) == 1 and all(lease is not None for lease in leases)
            assert leases[0].ref == leases[1].ref  # type: ignore[union-attr]
            grids.retire(1, below=2)  # version 2 applied: the files stay while plans hold them
            assert Path(leases[0].ref.risk_path).exists()  # type: ignore[union-attr]
            for lease in leases:
                lease.release()  # type: ignore[union-attr]
            assert grids.bytes == 0 and not list(grids.directory.glob("*.npy"))  # type: ignore[union-attr]

            # a plan whose request is cancelled while its grid is written: the file goes once written
            gate.clear()
            cancelled = asyncio.ensure_future(grids.publish(1, 2, risk, observed, 0.1, (0.0, 0.0), lambda: True))
            await asyncio.sleep(0.05)
            cancelled.cancel()
            with pytest.raises(asyncio.CancelledError):
                await cancelled
            gate.set()
            for _ in range(100):
                if grids.bytes == 0:
                    break
                await asyncio.sleep(0.02)
            assert grids.bytes == 0 and not list(grids.directory.glob("*.npy"))  # type: ignore[union-attr]
            again = await grids.publish(1, 2, risk, observed, 0.1, (0.0, 0.0), lambda: True)
            assert again is not None and Path(again.ref.risk_path).exists()
            again.release()
        finally:
            grids.close()

    asyncio.run(scenario())
    assert not (tmp_path / "plan-grids").exists()
