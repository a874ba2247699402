"""``POST /maps/import`` over HTTP: a map started from a saved Nav2 map or an OccupancyGrid, its cells as agreeing
scans, durable and replayed; a round trip through ``export/nav2`` byte for byte; bad files refused, nothing made."""

from __future__ import annotations

import io
import math
import sqlite3
import zipfile
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.factory import create_app
from app.maps import restore
from app.ros import messages_out
from app.ros.msgtypes import typestore
from app.storage import SqliteStorage, StorageUnavailable
from fuzzyocc import BayesMap, FuzzyEngine, FuzzyMap, GridSpec
from tests.app.formats.test_exports import _read_image, nav2_load
from tests.app.formats.test_saved_maps import form, nav2_yaml, pgm, png, zipped
from tests.conftest import error_message

ZIP = {"content-type": "application/zip"}
CDR = {"content-type": messages_out.CDR_MEDIA_TYPE}
#: lab's map under each model and engine, as POST /maps takes them and as the import's query does
SETTINGS: dict[str, dict[str, str]] = {"evidence": {}, "paper": {"engine": "paper"}, "bayes": {"model": "bayes"}}


def _prior_risks(kind: str, weight: int) -> np.ndarray:
    """What the import's levels -weight..weight read as, from fuzzyocc itself."""
    spec = GridSpec(origin=(0.0, 0.0), size=(1.0, 1.0), resolution=1.0)
    m = BayesMap(spec) if kind == "bayes" else FuzzyMap(spec, engine=FuzzyEngine.paper() if kind == "paper" else None)
    return m.prior_risks(weight).astype(np.float64)


def _scanned(client: TestClient, kit: Any, kind: str = "evidence", name: str = "lab", **extra: Any) -> None:
    """``name`` (lab's grid) after three scans: a wall seen from two poses, and one looking up."""
    assert client.post("/maps", json={**kit.MAP_2D, "name": name, **SETTINGS[kind], **extra}).status_code == 201
    scans = [kit.laser(wall=3.05), kit.laser(y=1.0, wall=3.05), kit.laser(x=-2.0, y=-3.0, theta=math.pi / 2, wall=6.05)]
    assert client.post(f"/maps/{name}/scans", json={"scans": scans}).status_code == 200


def _import(client: TestClient, body: bytes, headers: dict[str, str], **params: Any) -> Any:
    return client.post("/maps/import", params={"name": "copy", **params}, content=body, headers=headers)


def _files(archive: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(archive)) as z:
        return {name: z.read(name) for name in z.namelist()}


def _grid(client: TestClient, name: str) -> tuple[np.ndarray, np.ndarray]:
    risk = np.load(io.BytesIO(client.get(f"/maps/{name}/risk.npy").content))
    observed = np.load(io.BytesIO(client.get(f"/maps/{name}/risk.npy", params={"layer": "observed"}).content))
    return risk, observed


def _nothing_stored(client: TestClient) -> None:
    assert client.get("/maps").json() == []
    settings = client.app.state.settings  # type: ignore[attr-defined]
    with sqlite3.connect(settings.database_path) as db:
        assert db.execute("SELECT COUNT(*) FROM maps").fetchone()[0] == 0
        assert db.execute("SELECT COUNT(*) FROM batches").fetchone()[0] == 0


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize("kind", list(SETTINGS))
@pytest.mark.parametrize("image_format", ["pgm", "png"])
def test_a_trinary_export_imported_and_exported_again_gives_the_same_files(
        client: TestClient, kit: Any, kind: str, image_format: str) -> None:
    _scanned(client, kit, kind)
    exported = client.get("/maps/lab/export/nav2", params={"format": image_format}).content
    made = _import(client, exported, ZIP, **SETTINGS[kind])
    assert made.status_code == 201, made.text
    info = made.json()
    assert (info["name"], info["origin"], info["resolution"], info["shape"], info["version"], info["scans_fused"]) == \
        ("copy", [-5.0, -5.0], 0.1, [100, 100], 1, 0)
    again = client.get("/maps/copy/export/nav2", params={"format": image_format}).content
    assert _files(again) == _files(exported)  # map.yaml and the image, byte for byte
    meta, data = nav2_load(exported)  # and what map_server loads of them
    meta_again, data_again = nav2_load(again)
    assert meta_again == meta and np.array_equal(data_again, data)
    assert {-1, 0, 100} <= set(np.unique(data).tolist())


@pytest.mark.parametrize(("mode", "image_format"), [("trinary", "pgm"), ("scale", "png"), ("raw", "pgm"),
                                                    ("raw", "png")])
@pytest.mark.parametrize("weight", [1, 2, 4])
def test_every_mode_imports_each_cell_as_the_level_of_the_risk_nearest_its_occupancy(
        client: TestClient, kit: Any, mode: str, image_format: str, weight: int) -> None:
    _scanned(client, kit)
    params = {"mode": mode, "format": image_format, "free_thresh": "0.35", "occupied_thresh": "0.65"}
    exported = client.get("/maps/lab/export/nav2", params=params).content
    assert _import(client, exported, ZIP, prior_scans=weight).status_code == 201
    meta, data = nav2_load(exported)  # what map_server publishes of the file
    grey, _ = _read_image(meta["image"], _files(exported)[meta["image"]])
    occ = (1.0 - grey[::-1].T.astype(np.float32) / np.float32(255.0)).astype(np.float64)  # [i, j], as map_server
    published = data.reshape(100, 100).T  # [i, j]
    risks = _prior_risks("evidence", weight)
    nearest = risks[np.argmin(np.abs((occ if mode == "scale" else published / 100.0)[..., None] - risks), axis=-1)]
    expected = np.where(published == 100, risks[-1], np.where(published == 0, risks[0], nearest))
    risk, observed = _grid(client, "copy")
    assert np.array_equal(observed, published != -1)
    assert np.array_equal(risk[observed], expected[observed].astype(np.float32))
    assert np.all(risk[~observed] == 0.5)
    if mode != "trinary":
        assert len(np.unique(risk[observed])) > 2  # graded cells kept graded


def test_map_savers_two_files_as_a_form_make_the_map_they_describe(client: TestClient) -> None:
    grey = np.full((40, 60), 205, dtype=np.uint8)  # map_saver's unknown
    grey[10:30, 5:55] = 254  # a free room ...
    grey[10, 5:55] = 0  # ... with a wall along its top row (the highest y)
    meta = nav2_yaml(origin=[-1.0, -2.0, 0.0], resolution=0.05, free_thresh=0.196)
    body, content_type = form({"yaml": ("map.yaml", meta), "image": ("map.pgm", pgm(grey))})
    made = _import(client, body, {"content-type": content_type})
    assert made.status_code == 201, made.text
    info = made.json()
    assert (info["origin"], info["resolution"], info["shape"], info["frame_id"], info["version"]) == \
        ([-1.0, -2.0], 0.05, [60, 40], "map", 1)
    risk, observed = _grid(client, "copy")
    levels = _prior_risks("evidence", 2)
    wall_j = 40 - 1 - 10  # image row 10 from the top
    assert np.all(risk[5:55, wall_j] == np.float32(levels[-1]))
    assert np.all(risk[5:55, 40 - 30:wall_j] == np.float32(levels[0]))
    assert observed.sum() == 20 * 50 and np.all(risk[~observed] == 0.5)
    # black for free with negate: the same map
    negated = nav2_yaml(origin=[-1.0, -2.0, 0.0], resolution=0.05, free_thresh=0.196, negate=1)
    body, content_type = form({"yaml": ("map.yaml", negated), "image": ("map.pgm", pgm(255 - grey))})
    assert client.post("/maps/import", params={"name": "negated"}, content=body,
                       headers={"content-type": content_type}).status_code == 201
    assert np.array_equal(_grid(client, "negated")[0], risk)


def test_an_occupancy_grid_as_json_or_cdr_round_trips_with_its_frame(client: TestClient, kit: Any) -> None:
    _scanned(client, kit, frame_id="robot1/map")
    grid = client.get("/maps/lab/occupancy_grid").json()
    made = client.post("/maps/import", params={"name": "from_json"}, json=grid)
    assert made.status_code == 201, made.text
    assert made.json()["frame_id"] == "robot1/map"
    back = client.get("/maps/from_json/occupancy_grid").json()
    assert back["data"] == grid["data"] and back["info"]["origin"] == grid["info"]["origin"]
    assert back["header"]["frame_id"] == "robot1/map"
    cdr = client.get("/maps/lab/occupancy_grid.cdr").content
    assert client.post("/maps/import", params={"name": "from_cdr"}, content=cdr, headers=CDR).status_code == 201
    message = typestore().deserialize_cdr(client.get("/maps/from_cdr/occupancy_grid.cdr").content,
                                          messages_out.OCCUPANCY_GRID)
    assert message.data.tolist() == grid["data"] and message.header.frame_id == "robot1/map"
    # the query's frame wins over the message's
    assert client.post("/maps/import", params={"name": "elsewhere", "frame_id": "odom"}, json=grid).json()[
        "frame_id"] == "odom"


def test_the_prior_weighs_as_many_scans_as_prior_scans_says(client: TestClient, kit: Any) -> None:
    _scanned(client, kit)
    exported = client.get("/maps/lab/export/nav2").content
    for weight in (1, 3, 5):
        assert client.post("/maps/import", params={"name": f"w{weight}", "prior_scans": weight}, content=exported,
                           headers=ZIP).status_code == 201
        risk, observed = _grid(client, f"w{weight}")
        levels = _prior_risks("evidence", weight)
        assert set(np.unique(risk[observed]).tolist()) == {np.float32(levels[0]), np.float32(levels[-1])}
    assert kit.version(client, "w1") == 1 and client.get("/maps/w1").json()["scans_fused"] == 0


@pytest.mark.parametrize("kind", list(SETTINGS))
def test_an_obstacle_of_the_prior_seen_through_is_cleared_in_as_many_scans_as_scans_made_it(
        client: TestClient, kit: Any, kind: str) -> None:
    """A wall imported with the weight of 2 scans and the same wall made by 2 scans go in as many scans that
    see past it (the wall moved a metre away)."""
    _scanned(client, kit, kind, name="made")  # the wall at x = 3.05, seen by the first two scans
    exported = client.get("/maps/made/export/nav2").content
    assert _import(client, exported, ZIP, prior_scans=2, **SETTINGS[kind]).status_code == 201
    wall = (80, 50)  # the cell of (3.05, 0.05)
    counts = {}
    for name in ("made", "copy"):
        assert _grid(client, name)[0][wall] > 0.6
        for n in range(1, 30):
            assert client.post(f"/maps/{name}/scans", json={"scans": [kit.laser(wall=4.05)]}).status_code == 200
            if _grid(client, name)[0][wall] < 0.45:
                counts[name] = n
                break
    expected = {"evidence": 5, "paper": 2, "bayes": 3}[kind]  # as tests/fuzzyocc/test_prior.py finds cell by cell
    assert counts == {"made": expected, "copy": expected}


# ---------------------------------------------------------------- durable, replayed


def test_the_import_is_the_maps_first_batch_durable_and_replayed(make_settings: Callable[..., Any], kit: Any) -> None:
    settings = make_settings()
    with TestClient(create_app(settings)) as client:
        _scanned(client, kit)
        assert _import(client, client.get("/maps/lab/export/nav2").content, ZIP).status_code == 201
        risk, observed = _grid(client, "copy")
        storage = SqliteStorage(settings.database_path)
        stored = storage.load_map("copy")  # what a restart before a snapshot replays
        storage.close()
        assert stored is not None and [v for v, _ in stored.batches] == [1]
        assert stored.batches[0][1].startswith(b"FRP\x01")
        replayed = restore(stored)
        assert replayed.version == 1 and replayed.last_scan is None
        assert np.array_equal(replayed.map.risk(), risk) and np.array_equal(replayed.map.observed(), observed)
        assert client.post("/maps/copy/scans", json={"scans": [kit.laser(wall=2.05)]}).json()["version"] == 2
        after = _grid(client, "copy")
    with TestClient(create_app(settings)) as again:  # the graceful stop snapshotted it
        assert kit.version(again, "copy") == 2
        assert all(np.array_equal(a, b) for a, b in zip(_grid(again, "copy"), after))


def test_an_imported_maps_recording_has_no_scan_for_its_prior(client: TestClient, kit: Any) -> None:
    _scanned(client, kit)
    assert _import(client, client.get("/maps/lab/export/nav2").content, ZIP).status_code == 201
    recording = client.get("/maps/copy/export/mcap")
    assert recording.status_code == 200 and b"/map" in recording.content and b"/scan" not in recording.content
    assert client.get("/maps/copy/scans/last").status_code == 404


# ---------------------------------------------------------------- refused, nothing made


def _zip(**fields: Any) -> bytes:
    return zipped({"map.yaml": nav2_yaml(**fields), "map.pgm": pgm(np.full((20, 30), 254, dtype=np.uint8))})


BAD: list[tuple[str, Callable[[], tuple[bytes, dict[str, str]]], dict[str, Any], int, str]] = [
    ("a YAML that is not a map", lambda: (zipped({"map.yaml": b"- a\n- list\n", "map.pgm": b""}), ZIP), {}, 422,
     "map.yaml: not a Nav2 map YAML"),
    ("a rotated origin", lambda: (_zip(origin=[0.0, 0.0, 1.57]), ZIP), {}, 422, "origin[2] (yaw) is 1.57"),
    ("no image", lambda: (zipped({"map.yaml": nav2_yaml()}), ZIP), {}, 422, "image names 'map.pgm', which the zip"),
    ("an unreadable image", lambda: (zipped({"map.yaml": nav2_yaml(), "map.pgm": b"P5 nope"}), ZIP), {}, 422,
     "map.pgm: not"),
    ("another image's name", lambda: _form({"yaml": ("map.yaml", nav2_yaml()), "image": ("b.pgm", pgm(np.zeros((2, 2))))}),
     {}, 422, "image names 'map.pgm', but the 'image' part is 'b.pgm'"),
    ("pixels cut short", lambda: (zipped({"map.yaml": nav2_yaml(), "map.pgm": b"P5\n30 30\n255\n" + bytes(10)}), ZIP),
     {}, 422, "map.pgm: its pixels cannot be read"),
    ("over the cell limit", lambda: (zipped({"map.yaml": nav2_yaml(), "map.pgm": b"P5\n200 100\n255\n"}), ZIP), {},
     413, "200 x 100 = 20,000 cells, more than FUZZYRISK_MAX_MAP_CELLS (10,000)"),
    ("a zip bomb", lambda: (zipped({"map.yaml": nav2_yaml(), "map.pgm": b"P5\n90 90\n255\n" + bytes(4 * 2**20)}), ZIP),
     {}, 413, "map.pgm: it inflates to"),
    ("a body over the limit", lambda: (bytes(2 * 2**20), ZIP), {}, 413, "FUZZYRISK_MAX_BODY_BYTES"),
    ("another Content-Type", lambda: (b"hello", {"content-type": "text/plain"}), {}, 415, "is not a saved map"),
    ("a rotated grid", lambda: (_rotated_grid(), {"content-type": "application/json"}), {}, 422,
     "info.origin.orientation is a rotation"),
    ("a weight of no scan", lambda: (_zip(), ZIP), {"prior_scans": 0}, 422, "prior_scans"),
    ("an engine on a bayes map", lambda: (_zip(), ZIP), {"model": "bayes", "engine": "paper"}, 422,
     "engine applies to fuzzy maps only"),
    ("a misspelt setting", lambda: (_zip(), ZIP), {"range_sigmaa": 0.1}, 422, "range_sigmaa"),
    ("an invalid frame", lambda: (_zip(), ZIP), {"frame_id": "/map"}, 422, "frame_id"),
]


def _form(parts: dict[str, tuple[str | None, bytes]]) -> tuple[bytes, dict[str, str]]:
    body, content_type = form(parts)
    return body, {"content-type": content_type}


def _rotated_grid() -> bytes:
    import json

    from tests.app.ros.test_grid_in import grid_json
    return json.dumps(grid_json(yaw=0.5)).encode()


@pytest.mark.parametrize(("what", "make", "params", "status", "says"), BAD, ids=[b[0] for b in BAD])
def test_a_bad_file_is_refused_naming_what_is_wrong_and_nothing_is_made(
        make_client: Callable[..., TestClient], what: str, make: Callable[[], tuple[bytes, dict[str, str]]],
        params: dict[str, Any], status: int, says: str) -> None:
    client = make_client(max_map_cells=10_000, max_body_bytes=2**20)
    body, headers = make()
    refused = _import(client, body, headers, **params)
    assert refused.status_code == status, refused.text
    assert says in refused.text
    _nothing_stored(client)


def test_a_taken_name_is_refused_before_the_body_is_read_and_the_map_is_left_alone(client: TestClient,
                                                                                  kit: Any) -> None:
    _scanned(client, kit, name="copy")
    before = _grid(client, "copy")
    refused = _import(client, b"not even a zip", ZIP)
    assert refused.status_code == 409 and "'copy' exists" in error_message(refused)
    assert kit.version(client, "copy") == 1 and np.array_equal(_grid(client, "copy")[0], before[0])


def test_an_import_over_the_maps_budget_is_refused_before_its_cells_are_decoded(
        make_client: Callable[..., TestClient], kit: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    client = make_client(max_maps=1)
    _scanned(client, kit)
    decoded: list[int] = []
    from app.formats import saved_maps

    monkeypatch.setattr(saved_maps.SavedMap, "cells", lambda self: decoded.append(1))
    refused = _import(client, client.get("/maps/lab/export/nav2").content, ZIP)
    assert refused.status_code == 507 and "FUZZYRISK_MAX_MAPS" in error_message(refused)
    assert decoded == [] and [m["name"] for m in client.get("/maps").json()] == ["lab"]


def test_an_import_whose_first_batch_cannot_be_stored_leaves_no_map(
        client: TestClient, kit: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    archive = _zip()

    def full(self: Any, records: Any) -> list[int]:
        raise StorageUnavailable("database or disk is full")

    monkeypatch.setattr(SqliteStorage, "append_batches", full)
    refused = _import(client, archive, ZIP)
    assert refused.status_code == 503 and refused.json()["code"] == "STORAGE_UNAVAILABLE"
    _nothing_stored(client)
    monkeypatch.undo()
    assert _import(client, archive, ZIP).status_code == 201  # the name is free again


def test_an_import_whose_first_batch_fails_to_apply_leaves_no_map(
        make_settings: Callable[..., Any], monkeypatch: pytest.MonkeyPatch) -> None:
    from app.maps import writepath

    def broken(built: Any, batch: Any) -> Any:
        raise MemoryError("simulated")

    monkeypatch.setattr(writepath, "integrate", broken)
    with TestClient(create_app(make_settings()), raise_server_exceptions=False) as client:  # a 500 is answered
        refused = _import(client, _zip(), ZIP)
        assert refused.status_code == 500
        _nothing_stored(client)


def test_the_import_needs_the_api_key_when_one_is_set(make_client: Callable[..., TestClient]) -> None:
    key = "k" * 32
    client = make_client(api_key=key)
    assert _import(client, _zip(), ZIP).status_code == 401
    made = _import(client, _zip(), {**ZIP, "Authorization": f"Bearer {key}"})
    assert made.status_code == 201 and made.json()["shape"] == [30, 20]


def test_a_png_with_transparency_imports_its_transparent_cells_as_never_observed(client: TestClient) -> None:
    grey = np.full((4, 5), 254, dtype=np.uint8)
    alpha = np.full((4, 5), 255, dtype=np.uint8)
    alpha[0, :] = 0
    archive = zipped({"map.yaml": nav2_yaml(image="map.png"), "map.png": png(grey, alpha)})
    assert _import(client, archive, ZIP).status_code == 201
    _, observed = _grid(client, "copy")
    assert observed.shape == (5, 4) and not observed[:, 3].any() and observed[:, :3].all()
