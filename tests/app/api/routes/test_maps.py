"""Map resources: create, list, get, delete (docs/api.md) and its 4xx answers."""

from __future__ import annotations

import gc
import weakref
from typing import Any

import pytest
from fastapi.testclient import TestClient
from tests.conftest import error_message


def test_create_answers_201_with_the_full_map_info(client: TestClient, kit: Any) -> None:
    response = client.post("/maps", json=kit.MAP_2D)
    assert response.status_code == 201
    info = response.json()
    assert info["name"] == "lab" and info["dimensions"] == 2 and info["model"] == "fuzzy"
    assert info["resolution"] == 0.1 and info["origin"] == [-5.0, -5.0] and info["size"] == [10.0, 10.0]
    assert info["shape"] == [100, 100]
    assert info["sensor"]["range_sigma"] == 0.03
    assert info["scans_fused"] == 0 and info["version"] == 0
    assert info["created"] == info["updated"]


def test_a_new_map_is_unknown_everywhere(lab: TestClient, kit: Any) -> None:
    risk = kit.risk_npy(lab, "lab")
    assert risk.shape == (100, 100) and risk.dtype.name == "float32"
    assert (risk == 0.5).all()


def test_list_and_get_show_every_map_by_name(client: TestClient, kit: Any) -> None:
    client.post("/maps", json={**kit.MAP_2D, "name": "b-map"})
    client.post("/maps", json={**kit.MAP_3D, "name": "a.map", "model": "bayes"})
    listed = client.get("/maps").json()
    assert [m["name"] for m in listed] == ["a.map", "b-map"]
    one = client.get("/maps/a.map").json()
    assert one["dimensions"] == 3 and one["model"] == "bayes" and one["shape"] == [40, 40, 15]


def test_dimensions_default_to_the_length_of_origin(client: TestClient, kit: Any) -> None:
    body = {k: v for k, v in kit.MAP_3D.items() if k != "dimensions"}
    assert client.post("/maps", json=body).json()["dimensions"] == 3


def test_a_taken_name_answers_409_and_keeps_the_first_map(lab: TestClient, kit: Any) -> None:
    response = lab.post("/maps", json={**kit.MAP_2D, "resolution": 0.5})
    assert response.status_code == 409
    assert "lab" in error_message(response)
    assert lab.get("/maps/lab").json()["resolution"] == 0.1


def test_delete_answers_204_then_the_map_is_gone(lab: TestClient) -> None:
    assert lab.delete("/maps/lab").status_code == 204
    assert lab.get("/maps/lab").status_code == 404
    assert lab.delete("/maps/lab").status_code == 404
    assert lab.get("/maps").json() == []


def test_unknown_map_answers_404_everywhere(client: TestClient, kit: Any) -> None:
    for method, path, body in [
        ("GET", "/maps/nope", None), ("DELETE", "/maps/nope", None),
        ("POST", "/maps/nope/scans", {"scans": [kit.laser()]}), ("GET", "/maps/nope/risk", None),
        ("POST", "/maps/nope/risk/query", {"points": [[0, 0]]}), ("GET", "/maps/nope/scans/last", None),
        ("GET", "/maps/nope/occupancy_grid", None), ("GET", "/maps/nope/export/nav2", None),
    ]:
        response = client.request(method, path, json=body)
        assert response.status_code == 404, (method, path)
        assert "nope" in error_message(response)


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"name": "../etc"}, "name"),
        ({"name": ".hidden"}, "name"),
        ({"name": "a" * 65}, "name"),
        ({"name": "with space"}, "name"),
        ({"name": "é"}, "name"),
        ({"resolution": 0}, "resolution"),
        ({"resolution": -0.1}, "resolution"),
        ({"origin": [0.0]}, "origin"),
        ({"origin": [0.0, 0.0, 0.0]}, "origin"),  # dimensions says 2
        ({"size": [10.0, -1.0]}, "size"),
        ({"size": [10.0]}, "size"),
        ({"dimensions": 4}, "dimensions"),
        ({"model": "octomap"}, "model"),
        ({"sensor": {"range_sigma": -0.1}}, "range_sigma"),
        ({"colour": "red"}, "colour"),  # a typo in a field name is refused, not ignored
    ],
)
def test_bad_map_requests_answer_422_naming_the_field(client: TestClient, kit: Any, change: dict, needle: str) -> None:
    response = client.post("/maps", json={**kit.MAP_2D, **change})
    assert response.status_code == 422
    assert needle in str(response.json())
    assert client.get("/maps").json() == []


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_geometry_is_refused(client: TestClient, token: str) -> None:
    # Python's json.dumps writes these tokens; they must not sneak into a map's geometry
    body = '{"name": "x", "resolution": 0.1, "origin": [0, %s], "size": [1, 1]}' % token
    response = client.post("/maps", content=body, headers={"Content-Type": "application/json"})
    assert response.status_code == 422
    assert "origin" in str(response.json())


def test_a_map_above_the_cell_limit_is_refused_with_the_setting_named(make_client: Any, kit: Any) -> None:
    client = make_client(max_map_cells=5_000)
    response = client.post("/maps", json=kit.MAP_2D)  # 10 000 cells
    assert response.status_code == 422
    assert "FUZZYRISK_MAX_MAP_CELLS" in error_message(response)
    assert client.get("/maps").json() == []


def test_a_bad_name_in_the_path_answers_422(client: TestClient) -> None:
    assert client.get("/maps/bad name!").status_code == 422


def test_a_size_that_is_not_whole_cells_is_rounded_up_and_reported_as_built(client: TestClient) -> None:
    info = client.post("/maps", json={"name": "odd", "resolution": 0.07, "origin": [0.0, 0.0], "size": [1.0, 0.3]})
    assert info.status_code == 201, info.text
    assert info.json()["shape"] == [15, 5] and info.json()["size"] == [1.05, 0.35]
    inside = client.post("/maps/odd/risk/query", json={"points": [[1.04, 0.34]]})
    outside = client.post("/maps/odd/risk/query", json={"points": [[1.06, 0.1]]})
    assert inside.status_code == 200 and outside.status_code == 422


def test_a_deleted_maps_memory_is_freed_at_the_delete(lab: TestClient, kit: Any) -> None:
    # every map was a reference cycle (its storage held a bound method of the map), so a deleted
    # map stayed in memory until the cyclic garbage collector ran, after the delete had returned its
    # memory to the system: 25 maps of 16 M cells made and deleted, round after round, kept up to 400 MiB
    assert lab.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200
    held = weakref.ref(lab.app.state.service.maps.entry("lab").map)  # type: ignore[attr-defined]
    gc.collect()
    gc.disable()
    try:
        assert lab.delete("/maps/lab").status_code == 204
        assert held() is None
    finally:
        gc.enable()
