"""A store written by earlier code gives the same maps with today's, bit for bit (``tests/data/stored_log``).

The store was written before the 3-D rotations (point clouds, sensor poses, TF lookups) moved from
hand-written code to scipy's ``Rotation`` and ``Slerp``: a snapshot and the batches logged after it for
two maps, a log alone for a third. Replayed at a start, it must give each map as the code that wrote it
held it. Sent again (the same JSON, ``.npy``, CDR and bag bodies with the same 3-D poses), the requests
must give the same maps too: what the rotations compute at ingest is what the log keeps.
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

from app.storage.backup import DATABASE
from tests.conftest import DATA_DIR

STORED = DATA_DIR / "stored_log"
#: As the store was written: "flat" and "hall" have a snapshot and a log after it, "bayes" a log only.
SNAPSHOT_EVERY = 4


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


@pytest.mark.parametrize("name", ["flat", "hall", "bayes"])
def test_the_same_requests_give_the_same_maps(make_client: Callable[..., TestClient], name: str) -> None:
    stored = _stored()
    client = make_client(snapshot_every=SNAPSHOT_EVERY)
    (spec,) = [spec for spec in stored["maps"] if spec["name"] == name]
    assert client.post("/maps", json=spec).status_code == 201
    for item in stored["requests"]:
        if item["map"] == name:
            response = send(client, item)
            assert response.status_code == 200, response.text
    _assert_same_map(held_arrays(client, name), _expected(name))
