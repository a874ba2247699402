"""A store written by earlier code gives the same maps with today's, bit for bit (``tests/data/stored_log``).

The store was written before the 3-D rotations (point clouds, sensor poses, TF lookups) moved from
hand-written code to scipy's ``Rotation`` and ``Slerp``: a snapshot and the batches logged after it for
two maps, a log alone for a third. Replayed at a start, it must give each map as the code that wrote it
held it. Sent again (the same JSON, ``.npy``, CDR and bag bodies with the same 3-D poses), the requests
must give the same batch records (every point in the map frame, as the rotations placed it at ingest)
and the same maps. A bag's scans are placed by TF lookups, which scipy computes differently from the
code before it in the last bits (poses 4.4e-16 apart at most on these bags): their points are compared
to 1e-12 m, and the maps they went into bit for bit.
"""

from __future__ import annotations

import base64
import gzip
import io
import json
import shutil
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.maps import logcodec
from app.storage.backup import DATABASE
from fuzzyocc import PointCloud
from tests.conftest import DATA_DIR

STORED = DATA_DIR / "stored_log"
#: As the store was written: "flat" and "hall" have a snapshot and a log after it, "bayes" a log only.
SNAPSHOT_EVERY = 4
#: No snapshot: every batch stays in the log, to be compared with ``batches.npz``.
NEVER = 10**9


def send(client: TestClient, item: dict[str, Any]) -> Any:
    """Post one stored request (``requests.json.gz``); the answer."""
    url = f"/maps/{item['map']}/{item['kind']}"
    if "json" in item:
        return client.post(url, json=item["json"], params=item["params"])
    return client.post(url, content=base64.b64decode(item["base64"]), params=item["params"],
                       headers={"Content-Type": item["content_type"]})


def held_arrays(client: TestClient, name: str) -> dict[str, np.ndarray]:
    """The map's ``to_arrays()`` as the service holds it, and its risk as ``GET /maps/{name}/risk.npy`` serves it."""
    arrays = dict(client.app.state.service.maps.entry(name).map.to_arrays())  # type: ignore[attr-defined]
    response = client.get(f"/maps/{name}/risk.npy")
    assert response.status_code == 200, response.text
    arrays["risk"] = np.load(io.BytesIO(response.content), allow_pickle=False)
    return arrays


def logged_batches(client: TestClient, name: str) -> dict[int, bytes]:
    """Version -> the batch record the service stored (its scans in the map frame, as ``app.maps.logcodec`` encodes),
    without the stamps the code that wrote ``batches.npz`` did not keep (each scan has one now: checked here)."""
    stored = client.app.state.service.storage.load_map(name)  # type: ignore[attr-defined]
    assert stored is not None and stored.snapshot is None, "a snapshot took batches out of the log"
    unstamped = {}
    for version, payload in stored.batches:
        scans = logcodec.decode(payload)
        if isinstance(scans, list):
            assert all(scan.stamp_ns is not None for scan in scans), f"{name} version {version}: a scan has no stamp"
            payload = logcodec.encode([scan.stamped(None) for scan in scans])
        unstamped[version] = payload
    return unstamped


def _stored() -> dict[str, Any]:
    with gzip.open(STORED / "requests.json.gz", "rt") as f:
        return dict(json.load(f))


def _expected(name: str) -> dict[str, np.ndarray]:
    with np.load(STORED / "maps.npz", allow_pickle=False) as saved:
        return {key.split(".", 1)[1]: saved[key] for key in saved.files if key.startswith(f"{name}.")}


def _assert_same_map(held: dict[str, np.ndarray], expected: dict[str, np.ndarray]) -> None:
    assert sorted(held) == sorted(expected)
    assert expected["observed"].any(), "nothing observed: the comparison would prove nothing"
    for key, value in expected.items():
        assert held[key].dtype == value.dtype and held[key].shape == value.shape, key
        assert held[key].tobytes() == value.tobytes(), f"{key} differs in {np.sum(held[key] != value)} entries"


def test_a_store_written_before_replays_to_the_same_maps(make_client: Callable[..., TestClient],
                                                          tmp_path: Any) -> None:
    (tmp_path / "data").mkdir()
    shutil.copyfile(STORED / DATABASE, tmp_path / "data" / DATABASE)
    client = make_client(snapshot_every=SNAPSHOT_EVERY)
    names = [spec["name"] for spec in _stored()["maps"]]
    assert sorted(m["name"] for m in client.get("/maps").json()) == sorted(names)
    for name in names:
        assert client.get(f"/maps/{name}").status_code == 200
        entry = client.app.state.service.maps.entry(name)  # type: ignore[attr-defined]
        assert entry.snapshot_version < entry.version  # batches were replayed, not only a snapshot read
        _assert_same_map(held_arrays(client, name), _expected(name))


def _assert_same_batch(name: str, version: int, logged: bytes, expected: bytes) -> None:
    """The same scans, bit for bit, as fused: clouds are now stored as taken (sensor-frame points and pose) where they
    were stored in the map frame, so their records differ while the map-frame points they decode to must not."""
    if logged == expected:
        return
    ours, theirs = logcodec.decode(logged), logcodec.decode(expected)
    assert isinstance(ours, list) and isinstance(theirs, list) and len(ours) == len(theirs), f"{name} version {version}"
    for k, (a, b) in enumerate(zip(ours, theirs, strict=True)):
        assert type(a) is type(b), f"{name} version {version} scan {k}"
        if isinstance(a, PointCloud) and isinstance(b, PointCloud):
            assert a.points.shape == b.points.shape, f"{name} version {version} scan {k}"
            moved = int(np.sum(a.points != b.points))
            assert a.points.tobytes() == b.points.tobytes(), \
                f"{name} version {version} scan {k}: {moved} of {a.points.size} coordinates differ"
            assert a.origin == b.origin and (a.range_max, a.registration_sigma) == (b.range_max, b.registration_sigma)
        else:
            assert logcodec.encode([a]) == logcodec.encode([b]), f"{name} version {version} scan {k}"


def _assert_placed_alike(logged: bytes, expected: bytes) -> None:
    """A bag's batch: the same scans, placed by TF lookups that may differ from the earlier code's in the last bits."""
    ours, theirs = logcodec.decode(logged), logcodec.decode(expected)
    assert [type(a) for a in ours] == [type(b) for b in theirs]
    for a, b in zip(ours, theirs):
        if isinstance(a, PointCloud) and isinstance(b, PointCloud):
            assert np.allclose(a.points, b.points, rtol=0.0, atol=1e-12) and np.allclose(a.origin, b.origin, atol=1e-12)
        else:
            assert np.allclose(a.pose, b.pose, rtol=0.0, atol=1e-12) and a.ranges.tobytes() == b.ranges.tobytes()


@pytest.mark.parametrize("name", ["flat", "hall", "bayes"])
def test_the_same_requests_give_the_same_points_and_maps(make_client: Callable[..., TestClient], name: str) -> None:
    stored = _stored()
    client = make_client(snapshot_every=NEVER)
    (spec,) = [spec for spec in stored["maps"] if spec["name"] == name]
    assert client.post("/maps", json=spec).status_code == 201
    from_bags: set[int] = set()
    version = 0
    for item in stored["requests"]:
        if item["map"] == name:
            response = send(client, item)
            assert response.status_code == 200, response.text
            if item["kind"] == "bags":
                from_bags |= set(range(version + 1, response.json()["version"] + 1))
            version = response.json()["version"]
    logged = logged_batches(client, name)
    with np.load(STORED / "batches.npz", allow_pickle=False) as saved:
        expected = {int(key.split(".")[1]): saved[key].tobytes() for key in saved.files if key.startswith(f"{name}.")}
    assert sorted(logged) == sorted(expected)
    for v, payload in expected.items():
        if v in from_bags:
            _assert_placed_alike(logged[v], payload)
        else:  # every point where the earlier code put it, to the last bit: a map may absorb a point an ulp off
            _assert_same_batch(name, v, logged[v], payload)
    _assert_same_map(held_arrays(client, name), _expected(name))
