"""A fuzzy map's engine through the API: presets, full definitions, refusals, restarts, old maps."""

from __future__ import annotations

import copy
import json
import sqlite3
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Any

import numpy as np
import pytest

from app.schemas import MapCreate
from fastapi.testclient import TestClient

from app.maps import logcodec
from app.storage import BatchRecord, SqliteStorage
from fuzzyocc import FuzzyEngine, FuzzyMap, GridSpec, LaserScan, SensorModel, presets
from fuzzyocc.engine import even_output_mfs
from fuzzyocc.engine_spec import engine_to_dict
from fuzzyocc.membership import ladder
from fuzzyocc.presets import PRESETS


def stepping_engine(labels: tuple[str, ...], output_peaks: list[float] | None = None, **ops: Any) -> FuzzyEngine:
    """An engine over ``labels`` (risk order, "UNK" among them) whose rule steps the state one label toward the
    evidence; inputs a ladder 1 sigma apart ending on the surface, UNK full from +1.5 sigma."""
    distance_order = tuple(lab for lab in labels if lab != "UNK") + ("UNK",)
    peaks = [float(k - len(labels) + 2) for k in range(len(labels) - 1)] + [1.5]
    index = {lab: k for k, lab in enumerate(labels)}
    rules = [[cur if new == "UNK" else labels[index[cur] + int(np.sign(index[new] - index[cur]))] for new in labels]
             for cur in labels]
    outputs = even_output_mfs(labels) if output_peaks is None else dict(zip(labels, ladder(output_peaks)))
    return FuzzyEngine(labels, "UNK", dict(zip(distance_order, ladder(peaks))), outputs, rules, **ops)


NINE = stepping_engine(("EMP", "MPE", "PE", "SE", "UNK", "SO", "PO", "MPO", "OCC"), and_op="product", or_op="probsum")
# 16 labels, UNK 8th: outputs evenly spaced up to UNK's peak at 0.5, then 7 wider steps to 1
SIXTEEN = stepping_engine(tuple(f"E{k}" for k in range(7)) + ("UNK",) + tuple(f"O{k}" for k in range(8)),
                          [k / 14 for k in range(8)] + np.linspace(8 / 14, 1.0, 8).tolist())


def as_scan(body: dict[str, Any]) -> LaserScan:
    """The library's LaserScan for a JSON LaserScan of these tests (finite ranges only)."""
    pose = body["pose"]
    return LaserScan(pose=(pose["x"], pose["y"], pose["theta"]), angle_min=body["angle_min"],
                     angle_increment=body["angle_increment"], ranges=np.array(body["ranges"], dtype=float),
                     range_min=body["range_min"], range_max=body["range_max"])


def scans(kit: Any, n: int) -> list[dict[str, Any]]:
    return [kit.laser(x=0.2 * k, y=-0.1 * k, theta=0.2 * k, wall=2.05 + 0.13 * k) for k in range(n)]


def library_map(kit: Any, engine: FuzzyEngine | None, bodies: list[dict[str, Any]]) -> FuzzyMap:
    spec = kit.MAP_2D
    fused = FuzzyMap(GridSpec(origin=spec["origin"], size=spec["size"], resolution=spec["resolution"]),
                     SensorModel(**spec["sensor"]), engine)
    for body in bodies:
        fused.integrate_batch([as_scan(body)])
    return fused


def stored_maps(client: TestClient) -> list[str]:
    return list(stored_meta(client))


def stored_meta(client: TestClient) -> dict[str, dict[str, Any]]:
    path = client.app.state.settings.database_path  # type: ignore[attr-defined]
    with sqlite3.connect(path) as db:
        return {name: json.loads(meta) for name, meta in db.execute("SELECT name, meta FROM maps")}


# ---------------------------------------------------------------- choosing an engine
def test_a_map_without_engine_gets_the_default_preset(client: TestClient, kit: Any) -> None:
    info = client.post("/maps", json={k: v for k, v in kit.MAP_2D.items() if k != "engine"}).json()
    default = presets.preset(presets.DEFAULT_PRESET)
    assert info["engine"] == {"preset": presets.DEFAULT_PRESET, "definition": engine_to_dict(default)}


def test_a_preset_name_chooses_that_engine_and_get_shows_it(client: TestClient, kit: Any) -> None:
    assert client.post("/maps", json={**kit.MAP_2D, "engine": "paper"}).status_code == 201
    engine = client.get("/maps/lab").json()["engine"]
    assert engine == {"preset": "paper", "definition": engine_to_dict(FuzzyEngine.paper())}
    assert client.get("/maps").json()[0]["engine"] == engine


def test_a_full_definition_is_taken_and_shown_as_given(client: TestClient, kit: Any) -> None:
    definition = engine_to_dict(NINE)
    created = client.post("/maps", json={**kit.MAP_2D, "engine": definition})
    assert created.status_code == 201, created.text
    assert created.json()["engine"] == {"preset": None, "definition": definition}
    assert client.get("/maps/lab").json()["engine"] == {"preset": None, "definition": definition}


@pytest.mark.parametrize("engine", [
    {"preset": "paper", "definition": engine_to_dict(FuzzyEngine.paper())},  # as GET shows it
    {"preset": "paper"},
    {"preset": "paper", "definition": None},
])  # fmt: skip
def test_the_engine_object_get_shows_is_taken_with_its_preset(client: TestClient, kit: Any,
                                                              engine: dict[str, Any]) -> None:
    created = client.post("/maps", json={**kit.MAP_2D, "engine": engine})
    assert created.status_code == 201, created.text
    assert created.json()["engine"] == {"preset": "paper", "definition": engine_to_dict(FuzzyEngine.paper())}
    assert stored_meta(client)["lab"]["engine"]["preset"] == "paper"  # as asked for


def test_the_engine_object_with_a_definition_alone_is_the_definition(client: TestClient, kit: Any) -> None:
    created = client.post("/maps", json={**kit.MAP_2D, "engine": {"preset": None, "definition": engine_to_dict(NINE)}})
    assert created.status_code == 201, created.text
    assert created.json()["engine"] == {"preset": None, "definition": engine_to_dict(NINE)}
    assert stored_meta(client)["lab"]["engine"] == {"preset": None, "definition": engine_to_dict(NINE)}


def test_a_definition_equal_to_a_preset_is_shown_under_its_name(client: TestClient, kit: Any) -> None:
    definition = engine_to_dict(FuzzyEngine.paper())
    del definition["normalize"]  # a field with a default may be left out
    info = client.post("/maps", json={**kit.MAP_2D, "engine": definition}).json()
    assert info["engine"]["preset"] == "paper"


def test_the_stored_meta_holds_the_preset_asked_for_and_the_full_definition(client: TestClient, kit: Any) -> None:
    client.post("/maps", json={**kit.MAP_2D, "engine": "paper"})
    client.post("/maps", json={**kit.MAP_2D, "name": "nine", "engine": engine_to_dict(NINE)})
    meta = stored_meta(client)
    assert meta["lab"]["engine"] == {"preset": "paper", "definition": engine_to_dict(FuzzyEngine.paper())}
    assert meta["nine"]["engine"] == {"preset": None, "definition": engine_to_dict(NINE)}


def test_a_bayes_map_has_no_engine(client: TestClient, kit: Any) -> None:
    info = client.post("/maps", json={**kit.MAP_2D, "model": "bayes"}).json()
    assert info["engine"] is None


def test_the_documented_engine_example_makes_a_map(client: TestClient, kit: Any) -> None:
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    (example,) = schemas["EngineDefinition"]["examples"]
    created = client.post("/maps", json={**kit.MAP_2D, "engine": example})
    assert created.status_code == 201, created.text
    assert client.post("/maps/lab/scans", json={"scans": [kit.laser()]}).status_code == 200


def test_sixteen_labels_are_accepted(client: TestClient, kit: Any) -> None:
    created = client.post("/maps", json={**kit.MAP_2D, "engine": engine_to_dict(SIXTEEN)})
    assert created.status_code == 201, created.text
    body = scans(kit, 1)[0]
    assert client.post("/maps/lab/scans", json={"scans": [body]}).status_code == 200
    assert kit.risk_npy(client, "lab").tobytes() == library_map(kit, SIXTEEN, [body]).risk().tobytes()


# ---------------------------------------------------------------- refusals
def _edit(path: str, value: Any) -> dict[str, Any]:
    """The paper's definition with the value at a dotted path replaced."""
    d = copy.deepcopy(engine_to_dict(FuzzyEngine.paper()))
    *parents, last = path.split(".")
    node = d
    for key in parents:
        node = node[key]
    node[last] = value
    return d


def _too_many_labels() -> dict[str, Any]:
    labels = [f"L{k}" for k in range(8)] + ["UNK"] + [f"H{k}" for k in range(8)]  # 17
    return {**engine_to_dict(FuzzyEngine.paper()), "labels": labels}


def _gap() -> dict[str, Any]:
    d = _edit("input_mfs.MPE", {"type": "triangle", "left": -5.0, "peak": -4.5, "right": -4.0})
    d["input_mfs"]["PE"] = {"type": "triangle", "left": -3.0, "peak": -2.5, "right": -2.0}
    return d


BAD = [
    ("unknown-label-concluded", _edit("rules.PO.EMP", "FOO"), "engine.rules['PO']['EMP'] concludes 'FOO'"),
    ("unknown-label-row", _edit("rules.FOO", {"EMP": "EMP"}), "engine.rules (rows) must name exactly the labels"),
    ("inputs-leave-a-gap", _gap(), "engine.input_mfs (distance axis, sigmas) do not cover the axis"),
    ("nan", _edit("input_mfs.PO.peak", float("nan")), "engine.input_mfs.PO.peak must be a finite number"),
    ("infinity", _edit("output_mfs.OCC.zero_at", float("-inf")), "engine.output_mfs.OCC.zero_at must be a finite"),
    ("too-many-labels", _too_many_labels(), "engine.labels has 17 labels; at most 16"),
    ("not-an-object", 3, f"engine must be a preset name (one of {sorted(PRESETS)}) or an engine definition"),
    ("labels-not-a-list", _edit("labels", "EMP MPE PE"), "engine.labels must be a list of label names"),
    ("mf-type", _edit("input_mfs.PO.type", "gaussian"), "engine.input_mfs.PO.type must be one of"),
    ("mf-order", _edit("input_mfs.PO.left", -1.5), "engine.input_mfs.PO: Triangle needs left < peak"),
    ("three-outputs-overlap", _edit("output_mfs.UNK", {"type": "triangle", "left": 0.2, "peak": 0.5, "right": 0.8}),
     "engine.output_mfs ['MPE', 'PE', 'UNK'] are all positive at risk 0.2005"),
    ("long-label", _edit("unknown", "U" * 40), "engine.unknown is 40 characters long; at most 32"),
    ("huge", {**engine_to_dict(FuzzyEngine.paper()), "extra": list(range(5000))}, "engine holds more than 2048"),
    ("unknown-field", _edit("colour", "red"), "engine.colour is not a field of an engine"),
    ("unknown-preset", "papr", f"no engine preset named 'papr'; the presets are {sorted(PRESETS)}"),
    ("long-preset", "p" * 100_000, f"engine is a 100000-character string; a preset name is one of {sorted(PRESETS)}"),
    # the object GET /maps/{name} shows
    ("object-preset-and-another-engine", {"preset": "paper", "definition": engine_to_dict(NINE)},
     "engine.preset is 'paper' but engine.definition is another engine (it equals no preset)"),
    ("object-preset-and-another-preset", {"preset": "paper", "definition": engine_to_dict(presets.preset("evidence"))},
     "engine.preset is 'paper' but engine.definition is another engine (it equals the preset 'evidence')"),
    ("object-empty", {"preset": None, "definition": None}, "engine needs a preset or a definition"),
    ("object-with-engine-fields", {"preset": "paper", "labels": ["EMP", "UNK"]},
     "engine.labels is not a field of the engine object"),
    ("object-nan", {"definition": _edit("input_mfs.PO.peak", float("nan"))},
     "engine.definition.input_mfs.PO.peak must be a finite number"),
    ("object-too-many-labels", {"definition": _too_many_labels()}, "engine.definition.labels has 17 labels"),
    ("object-three-outputs-overlap",
     {"definition": _edit("output_mfs.UNK", {"type": "triangle", "left": 0.2, "peak": 0.5, "right": 0.8})},
     "engine.definition.output_mfs ['MPE', 'PE', 'UNK'] are all positive"),
    ("object-unknown-preset", {"preset": "papr"}, "engine.preset: no engine preset named 'papr'"),
    ("object-preset-not-a-name", {"preset": 3}, "engine.preset must be a preset name"),
    ("object-definition-not-an-object", {"definition": "paper"}, "engine.definition must be an object of engine"),
]


@pytest.mark.parametrize(("engine", "needle"), [(e, n) for _, e, n in BAD], ids=[i for i, _, _ in BAD])
def test_a_bad_engine_answers_422_naming_the_field_and_creates_nothing(client: TestClient, kit: Any, engine: Any,
                                                                       needle: str) -> None:
    body = json.dumps({**kit.MAP_2D, "engine": engine})  # json.dumps writes NaN and Infinity tokens
    response = client.post("/maps", content=body, headers={"Content-Type": "application/json"})
    assert response.status_code == 422, response.text
    (error,) = response.json()["details"]
    assert error["loc"] == ["body", "engine"] and needle in error["msg"], error
    assert client.get("/maps").json() == [] and stored_maps(client) == []


def test_an_engine_on_a_bayes_map_is_refused(client: TestClient, kit: Any) -> None:
    response = client.post("/maps", json={**kit.MAP_2D, "model": "bayes", "engine": "paper"})
    assert response.status_code == 422
    assert "engine applies to fuzzy maps only" in str(response.json())
    assert client.get("/maps").json() == [] and stored_maps(client) == []


# ---------------------------------------------------------------- the engine at work, and across restarts
def test_a_custom_engine_fuses_as_the_library_map_with_that_engine(lab: TestClient, kit: Any) -> None:
    client = lab  # "lab" holds the paper's engine; "nine" the custom one, same geometry
    assert client.post("/maps", json={**kit.MAP_2D, "name": "nine", "engine": engine_to_dict(NINE)}).status_code == 201
    bodies = scans(kit, 3)
    for body in bodies:
        for name in ("lab", "nine"):
            assert client.post(f"/maps/{name}/scans", json={"scans": [body]}).status_code == 200
    nine = kit.risk_npy(client, "nine")
    assert nine.tobytes() == library_map(kit, NINE, bodies).risk().tobytes()
    assert kit.risk_npy(client, "lab").tobytes() == library_map(kit, None, bodies).risk().tobytes()
    assert not np.array_equal(nine, kit.risk_npy(client, "lab"))  # the engine matters


def test_after_a_restart_the_engine_and_the_risk_are_the_same(make_client: Any, kit: Any) -> None:
    first = make_client(snapshot_every=2)  # a snapshot at version 2, version 3 replayed
    first.post("/maps", json={**kit.MAP_2D, "engine": engine_to_dict(NINE)})
    bodies = scans(kit, 3)
    for body in bodies:
        assert first.post("/maps/lab/scans", json={"scans": [body]}).status_code == 200
    info, risk = first.get("/maps/lab").json(), kit.risk_npy(first, "lab")
    first.__exit__(None, None, None)

    second = make_client()
    assert second.get("/maps/lab").json() == info
    assert kit.risk_npy(second, "lab").tobytes() == risk.tobytes()
    more = scans(kit, 4)[3]  # and it goes on fusing with the same engine
    assert second.post("/maps/lab/scans", json={"scans": [more]}).status_code == 200
    assert kit.risk_npy(second, "lab").tobytes() == library_map(kit, NINE, [*bodies, more]).risk().tobytes()


@pytest.fixture
def tuned_default(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """The default preset moved on to another engine (as it will when a tuned engine lands)."""
    presets.preset.cache_clear()
    monkeypatch.setattr(presets, "PRESETS", {**presets.PRESETS, "tuned": lambda: NINE})
    monkeypatch.setattr(presets, "DEFAULT_PRESET", "tuned")
    yield
    presets.preset.cache_clear()


def test_a_map_stored_before_engines_keeps_the_papers_engine(make_settings: Any, make_client: Any, kit: Any,
                                                             tuned_default: None) -> None:
    # the meta and the batch exactly as the service wrote them before maps had an engine
    settings = make_settings()
    storage = SqliteStorage(settings.database_path)
    old_meta = {key: kit.MAP_2D[key] for key in ("name", "origin", "size", "resolution", "model", "sensor")}
    now = datetime.now(UTC).isoformat(timespec="milliseconds")
    storage.create_map("lab", {**old_meta, "created": now}, now)
    body = scans(kit, 1)[0]
    storage.append_batches([BatchRecord("lab", None, logcodec.encode([as_scan(body)]), now, 1)])
    storage.close()

    client = make_client()
    info = client.get("/maps/lab").json()
    assert info["version"] == 1
    assert info["engine"] == {"preset": "paper", "definition": engine_to_dict(FuzzyEngine.paper())}
    assert kit.risk_npy(client, "lab").tobytes() == library_map(kit, FuzzyEngine.paper(), [body]).risk().tobytes()
    # a new map meanwhile gets the new default; the old one is not moved to it
    fresh = client.post("/maps", json={k: v for k, v in {**kit.MAP_2D, "name": "fresh"}.items() if k != "engine"})
    assert fresh.json()["engine"]["preset"] == "tuned"
    assert client.get("/maps/lab").json()["engine"]["preset"] == "paper"


def test_a_copy_of_a_map_stored_before_engines_gets_the_papers_engine(make_settings: Any, make_client: Any, kit: Any,
                                                                      tuned_default: None) -> None:
    settings = make_settings()
    storage = SqliteStorage(settings.database_path)
    old_meta = {key: kit.MAP_2D[key] for key in ("name", "origin", "size", "resolution", "model", "sensor")}
    now = datetime.now(UTC).isoformat(timespec="milliseconds")
    storage.create_map("lab", {**old_meta, "created": now}, now)
    storage.close()

    client = make_client()
    old = client.get("/maps/lab").json()
    settings_shown = {key: value for key, value in old.items()
                      if key in MapCreate.model_fields}  # the settings, not the facts
    assert client.post("/maps", json={**settings_shown, "name": "copy"}).status_code == 201
    copy = client.get("/maps/copy").json()
    assert copy["engine"] == {"preset": "paper", "definition": engine_to_dict(FuzzyEngine.paper())}  # not "tuned"
    assert copy["frame_id"] == old["frame_id"] == "map"


def test_a_map_whose_preset_moved_on_is_shown_and_copied_with_its_own_engine(make_client: Any, kit: Any,
                                                                             tuned_default: None,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    first = make_client()
    assert first.post("/maps", json={**kit.MAP_2D, "engine": "tuned"}).status_code == 201  # NINE
    first.__exit__(None, None, None)
    presets.preset.cache_clear()
    monkeypatch.setattr(presets, "PRESETS", {**presets.PRESETS, "tuned": lambda: SIXTEEN})  # a new release's preset

    client = make_client()
    shown = client.get("/maps/lab").json()["engine"]
    assert shown == {"preset": None, "definition": engine_to_dict(NINE)}  # what it equals now: no preset
    assert client.post("/maps", json={**kit.MAP_2D, "name": "copy", "engine": shown}).status_code == 201
    assert client.get("/maps/copy").json()["engine"] == shown
