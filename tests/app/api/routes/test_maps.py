"""Map resources: create, list, get, delete (docs/api.md) and its 4xx answers."""

from __future__ import annotations

import gc
import weakref
from typing import Any

import pytest
from fastapi.testclient import TestClient
from tests.conftest import error_message

from fuzzyocc import FuzzyEngine
from fuzzyocc.engine_spec import engine_to_dict


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


def test_a_bayes_map_above_the_cell_limit_is_refused_with_the_setting_named(make_client: Any, kit: Any) -> None:
    client = make_client(max_map_cells=5_000)
    response = client.post("/maps", json={**kit.MAP_2D, "model": "bayes", "engine": None})  # 10 000 cells, all held
    assert response.status_code == 422
    assert "FUZZYRISK_MAX_MAP_CELLS" in error_message(response)
    assert client.get("/maps").json() == []


def test_a_fuzzy_map_counts_the_cells_it_holds_and_refuses_scans_once_full(make_client: Any, kit: Any) -> None:
    client = make_client(max_map_cells=2_000)
    made = client.post("/maps", json=kit.MAP_2D)  # a box of 10 000 cells: a fuzzy map holds none of them yet
    assert made.status_code == 201 and made.json()["held_cells"] == 0
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser(wall=3.0)]}).status_code == 200
    held = client.get("/maps/lab").json()["held_cells"]
    assert 0 < held < 10_000
    full = client.post("/maps/lab/scans", json={"scans": [kit.laser(x=-3.0, wall=6.0, beams=400)]})
    if full.status_code == 200:  # under the limit still: one more batch fills it
        full = client.post("/maps/lab/scans", json={"scans": [kit.laser(x=-3.0, y=-2.0, wall=6.0, beams=400)]})
    assert client.get("/maps/lab").json()["held_cells"] >= 2_000
    refused = client.post("/maps/lab/scans", json={"scans": [kit.laser(wall=3.0)]})
    assert refused.status_code == 507 and "FUZZYRISK_MAX_MAP_CELLS" in error_message(refused)
    version = client.get("/maps/lab").json()["version"]
    cleared = client.post("/maps/lab/clear", json={"min": [-5.0, -5.0], "max": [5.0, 5.0]})  # an edit is never refused
    assert cleared.status_code == 200 and cleared.json()["version"] == version + 1
    assert client.get("/maps/lab").json()["held_cells"] == 0
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser(wall=3.0)]}).status_code == 200


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


# ---------------------------------------------------------------- what GET shows, POST takes
#: The read-only facts of a map (docs/api.md): GET /maps/{name} shows them, POST /maps refuses them.
FACTS = ("shape", "bounds", "held_cells", "scans_fused", "version", "created", "updated", "history")


def settings_of(info: dict[str, Any]) -> dict[str, Any]:
    """What a client copies from a map's GET: everything but its name and the facts."""
    return {key: value for key, value in info.items() if key not in (*FACTS, "name")}


PAPER_BUT_NO_RETURNS_CUT = {**engine_to_dict(FuzzyEngine.paper()), "no_return_neighbours": 3}  # equals no preset
#: A map of each kind of setting, as a change to the kit's 2-D map "lab"
ROUND_TRIPS: dict[str, dict[str, Any]] = {
    "engine-default": {},
    "engine-preset": {"engine": "paper"},
    "engine-definition": {"engine": PAPER_BUT_NO_RETURNS_CUT},
    "bayes": {"model": "bayes"},
    "sensor": {"sensor": {"range_sigma": 0.05, "registration_sigma": 0.02, "range_sigma_per_m": 0.01}},
    "frame": {"frame_id": "robot1/map"},
    "dimensions-2": {"dimensions": 2},
    "dimensions-3": {"dimensions": 3, "resolution": 0.2, "origin": [-4.0, -4.0, -1.0], "size": [8.0, 8.0, 3.0]},
    "box": {"resolution": 0.07, "origin": [-1.5, -3.25], "size": [3.0, 6.3]},  # not whole cells: rounded up
    "box-odd-resolution": {"resolution": 1 / 3, "origin": [-50.0, -2.0], "size": [100.5, 4.0]},
}


@pytest.mark.parametrize("change", ROUND_TRIPS.values(), ids=ROUND_TRIPS.keys())
def test_a_maps_settings_as_get_shows_them_make_the_same_map(client: TestClient, kit: Any, change: dict) -> None:
    assert client.post("/maps", json={**kit.MAP_2D, **change}).status_code == 201
    scan = kit.laser(wall=1.0) if change.get("dimensions") != 3 else \
        {"pose": {"position": [0.0, 0.0, 0.5], "orientation": [0.0, 0.0, 0.0, 1.0]},
         "points": kit.cloud_sensor_points(distance=1.0).tolist(), "range_max": 10.0}
    assert client.post("/maps/lab/scans", json={"scans": [scan]}).status_code == 200
    old = client.get("/maps/lab").json()

    created = client.post("/maps", json={"name": "copy", **settings_of(old)})
    assert created.status_code == 201, created.text
    new = client.get("/maps/copy").json()
    assert settings_of(new) == settings_of(old)
    assert new["shape"] == old["shape"] and (new["version"], new["scans_fused"]) == (0, 0)  # a new map: no scans
    # the same settings at work: the same scan makes the same cells
    assert client.post("/maps/copy/scans", json={"scans": [scan]}).status_code == 200
    assert kit.risk_npy(client, "copy").tobytes() == kit.risk_npy(client, "lab").tobytes()


def test_the_facts_get_shows_are_refused_by_post_each_named_and_nothing_is_made(lab: TestClient) -> None:
    shown = lab.get("/maps/lab").json()
    response = lab.post("/maps", json={**shown, "name": "copy"})
    assert response.status_code == 422
    errors = response.json()["details"]
    assert [error["loc"] for error in errors] == [["body", fact] for fact in FACTS]
    assert all(error["msg"] == f"{error['loc'][1]} is read-only: GET /maps/{{name}} shows it, POST /maps does not "
               "take it; leave it out" for error in errors)
    assert [m["name"] for m in lab.get("/maps").json()] == ["lab"]


def test_the_openapi_document_marks_the_facts_read_only_and_every_other_field_is_taken(client: TestClient) -> None:
    # a field added to the map's settings is shown by GET and taken by POST (no list of fields to keep in step)
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    shown, taken = schemas["MapInfo"]["properties"], schemas["MapCreate"]["properties"]
    assert [key for key, field in shown.items() if field.get("readOnly")] == list(FACTS)
    assert [key for key in shown if key not in FACTS] == list(taken)
    assert not any(field.get("readOnly") for field in taken.values())
    assert set(schemas["MapInfo"]["required"]) == set(shown)  # every field is in every answer
    engine_taken = [choice.get("$ref") for choice in taken["engine"]["anyOf"]]
    assert shown["engine"]["anyOf"][0]["$ref"] == "#/components/schemas/EngineInfo" and \
        "#/components/schemas/EngineInfo" in engine_taken  # the very model GET shows
