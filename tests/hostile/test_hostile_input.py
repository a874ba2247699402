"""Hand-written hostile requests against a live server (API key set, small limits).

Each case is one request a careless or malicious client could send: NaN and infinities in
every number, arrays over the configured limits, deeply nested JSON, wrong dimensions, map
names with ``../`` (also percent-encoded), truncated and mislabelled binary bodies, wrong
content types, and a missing or wrong API key. Each must answer its 4xx with a JSON
error body (code, message, details) and leave every map exactly as it was (version and scan count of all maps).
"""

from __future__ import annotations

import http.client
import io
import json
import struct
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np
import pytest

from bench._client import ServerProcess

from .conftest import (
    API_KEY,
    CUBE,
    FLAT,
    MAX_BODY,
    MAX_QUERY_POINTS,
    MAX_RAYS,
    MAX_SCANS,
    SENT,
    assert_refused,
    auth,
    cloud,
    laser,
    map_states,
)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

F = FLAT["name"]
C = CUBE["name"]
V422 = frozenset({422})
TOO_BIG = frozenset({413, 422})
# FastAPI answers 400 "error parsing the body" when json.loads itself fails (RecursionError)
DEEP = frozenset({400, 422})


@dataclass(frozen=True)
class Req:
    """One hostile request: ``content`` is sent as the raw body (JSON text allows NaN tokens)."""

    id: str
    method: str
    path: str
    expect: frozenset[int]
    json: Any = None
    content: bytes | str | None = None
    params: dict[str, Any] | None = None
    headers: dict[str, str] = field(default_factory=dict)
    with_key: bool = True


def raw_json(obj: Any) -> str:
    """JSON text as Python writes it: NaN, Infinity and -Infinity come out as bare tokens."""
    return json.dumps(obj, allow_nan=True)


def scans(*items: dict[str, Any]) -> dict[str, Any]:
    return {"scans": list(items)}


def npy(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.save(out, array, allow_pickle=True)
    return out.getvalue()


BINARY_LASER_QUERY = {"x": 0.0, "y": 0.0, "theta": 0.0, "angle_min": -0.7, "angle_increment": 0.01,
                      "range_min": 0.05, "range_max": 10.0}
CLOUD_QUERY = {"x": 0.0, "y": 0.0, "z": 1.0, "range_max": 10.0}
OCTET = {"content-type": "application/octet-stream"}
NPY = {"content-type": "application/x-npy"}
JSON_CT = {"content-type": "application/json"}
PLAN = {"start": [-1.0, 0.0], "goal": [1.0, 0.5], "planner": "RRTConnect", "time_limit": 0.1, "robot_radius": 0.0}
GOOD_MAP = {"dimensions": 2, "resolution": 0.1, "origin": [0.0, 0.0], "size": [2.0, 2.0]}
BAD_NUMBERS = {"nan": float("nan"), "inf": float("inf"), "-inf": float("-inf")}
BAD_TOKENS = {"str-nan": "NaN", "str-inf": "inf", "overflow-1e999": "1e999"}


def _with(obj: dict[str, Any], path: tuple[Any, ...], value: Any) -> dict[str, Any]:
    """A deep copy of ``obj`` with ``obj[path[0]][path[1]]... = value``."""
    out = json.loads(json.dumps(obj))
    target = out
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return out


def _nonfinite_json(base: dict[str, Any], path: tuple[Any, ...]) -> list[tuple[str, str]]:
    """(label, body text) of ``base`` with the number at ``path`` replaced by NaN/inf in every spelling."""
    out = [(label, raw_json(_with(base, path, v))) for label, v in BAD_NUMBERS.items()]
    marker = "__HOSTILE__"
    text = raw_json(_with(base, path, marker))
    for label, token in BAD_TOKENS.items():
        # "NaN" and "inf" as JSON strings; 1e999 as a number that overflows to inf in the parser
        out.append((label, text.replace(f'"{marker}"', f'"{token}"' if label.startswith("str") else token)))
    return out


def nonfinite_cases() -> list[Req]:
    cases: list[Req] = []
    targets: list[tuple[str, str, dict[str, Any], tuple[Any, ...]]] = [
        ("pose.x", f"/maps/{F}/scans", scans(laser()), ("scans", 0, "pose", "x")),
        ("pose.y", f"/maps/{F}/scans", scans(laser()), ("scans", 0, "pose", "y")),
        ("pose.theta", f"/maps/{F}/scans", scans(laser()), ("scans", 0, "pose", "theta")),
        ("angle_min", f"/maps/{F}/scans", scans(laser()), ("scans", 0, "angle_min")),
        ("angle_increment", f"/maps/{F}/scans", scans(laser()), ("scans", 0, "angle_increment")),
        ("range_min", f"/maps/{F}/scans", scans(laser()), ("scans", 0, "range_min")),
        ("range_max", f"/maps/{F}/scans", scans(laser()), ("scans", 0, "range_max")),
        ("registration_sigma", f"/maps/{F}/scans", scans(laser()), ("scans", 0, "registration_sigma")),
        ("second-scan.pose.x", f"/maps/{F}/scans", scans(laser(), laser()), ("scans", 1, "pose", "x")),
        ("cloud.position", f"/maps/{C}/scans", scans(cloud()), ("scans", 0, "pose", "position", 2)),
        ("cloud.orientation", f"/maps/{C}/scans", scans(cloud()), ("scans", 0, "pose", "orientation", 3)),
        ("cloud.range_max", f"/maps/{C}/scans", scans(cloud()), ("scans", 0, "range_max")),
        ("map.origin", "/maps", {"name": "nf-origin", **GOOD_MAP}, ("origin", 0)),
        ("map.size", "/maps", {"name": "nf-size", **GOOD_MAP}, ("size", 1)),
        ("map.resolution", "/maps", {"name": "nf-res", **GOOD_MAP}, ("resolution",)),
        ("map.sensor", "/maps", {"name": "nf-sensor", **GOOD_MAP, "sensor": {"range_sigma": 0.03}},
         ("sensor", "range_sigma")),
        ("plan.start", f"/maps/{F}/plan", PLAN, ("start", 0)),
        ("plan.goal", f"/maps/{F}/plan", PLAN, ("goal", 1)),
        ("plan.time_limit", f"/maps/{F}/plan", PLAN, ("time_limit",)),
        ("plan.max_risk", f"/maps/{F}/plan", PLAN, ("max_risk",)),
        ("plan.robot_radius", f"/maps/{F}/plan", PLAN, ("robot_radius",)),
        ("plan.risk_weight", f"/maps/{F}/plan", PLAN, ("risk_weight",)),
        ("query.point", f"/maps/{F}/risk/query", {"points": [[0.0, 0.0], [0.5, 0.5]]}, ("points", 1, 0)),
        ("query.point-3d", f"/maps/{C}/risk/query", {"points": [[0.0, 0.0, 0.5]]}, ("points", 0, 2)),
    ]
    for field_name, path, base, where in targets:
        for label, text in _nonfinite_json(base, where):
            cases.append(Req(f"nonfinite-{field_name}-{label}", "POST", path, V422, content=text, headers=JSON_CT))
    # the binary upload carries its pose and geometry in the query
    ranges = np.full(100, 1.5, dtype="<f4").tobytes()
    for key in ("x", "y", "theta", "angle_min", "angle_increment", "range_min", "range_max", "registration_sigma"):
        for label, value in (("nan", "nan"), ("inf", "inf"), ("-inf", "-inf"), ("1e999", "1e999")):
            cases.append(Req(f"nonfinite-binary-{key}-{label}", "POST", f"/maps/{F}/scans", V422, content=ranges,
                             params={**BINARY_LASER_QUERY, key: value}, headers=OCTET))
    pts = np.tile([1.5, 0.0, 0.0], (10, 1)).astype("<f4").tobytes()
    for key in ("x", "z", "qw", "range_max"):
        cases.append(Req(f"nonfinite-binary-cloud-{key}", "POST", f"/maps/{C}/scans", V422, content=pts,
                         params={**CLOUD_QUERY, key: "nan"}, headers=OCTET))
    for key in ("z_min", "z_max"):
        cases.append(Req(f"nonfinite-risk-png-{key}", "GET", f"/maps/{C}/risk", V422,
                         params={"format": "png", key: "nan"}))
    cases.append(Req("nonfinite-nav2-free_thresh", "GET", f"/maps/{F}/export/nav2", V422,
                     params={"free_thresh": "nan"}))
    return cases


def npy_raw(shape: str, *, payload: bytes, descr: str = "<f4", fortran: bool = False) -> bytes:
    """A version 1.0 ``.npy`` whose header says what we like, followed by ``payload``."""
    header = f"{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}"
    total = 10 + len(header) + 1
    header = header + " " * ((64 - total % 64) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode("latin1") + payload


def deep(depth: int, open_: str = "[", close: str = "]") -> str:
    return open_ * depth + close * depth


def size_cases() -> list[Req]:
    big_ranges = np.full(MAX_RAYS + 1, 1.5, dtype="<f4")
    over_body = "[" + ",".join(["1.5"] * (MAX_BODY // 4 + 10)) + "]"
    return [
        Req("huge-ranges-json", "POST", f"/maps/{F}/scans", TOO_BIG,
            json=scans(laser(ranges=[1.5] * (MAX_RAYS + 1)))),
        Req("huge-batch", "POST", f"/maps/{F}/scans", TOO_BIG, json=scans(*[laser(beams=10)] * (MAX_SCANS + 1))),
        Req("huge-cloud-json", "POST", f"/maps/{C}/scans", TOO_BIG,
            json=scans(cloud(points=[[1.5, 0.0, 0.0]] * (MAX_RAYS + 1)))),
        Req("huge-ranges-binary", "POST", f"/maps/{F}/scans", TOO_BIG, content=big_ranges.tobytes(),
            params=BINARY_LASER_QUERY, headers=OCTET),
        Req("huge-ranges-npy", "POST", f"/maps/{F}/scans", TOO_BIG, content=npy(big_ranges), params=BINARY_LASER_QUERY,
            headers=NPY),
        Req("huge-cloud-binary", "POST", f"/maps/{C}/scans", TOO_BIG,
            content=np.tile([1.5, 0.0, 0.0], (MAX_RAYS + 1, 1)).astype("<f4").tobytes(), params=CLOUD_QUERY,
            headers=OCTET),
        Req("body-over-limit-json", "POST", f"/maps/{F}/scans", frozenset({413}),
            content='{"scans": [{"ranges": ' + over_body + "}]}", headers=JSON_CT),
        Req("body-over-limit-binary", "POST", f"/maps/{F}/scans", frozenset({413}),
            content=b"\0" * (MAX_BODY + 4), params=BINARY_LASER_QUERY, headers=OCTET),
        Req("body-over-limit-plan", "POST", f"/maps/{F}/plan", frozenset({413}), content=over_body, headers=JSON_CT),
        Req("huge-query", "POST", f"/maps/{F}/risk/query", TOO_BIG, json={"points": [[0.0, 0.0]] * (MAX_QUERY_POINTS + 1)}),
        Req("huge-map", "POST", "/maps", V422,
            json={"name": "too-big", "dimensions": 2, "resolution": 0.001, "origin": [0, 0], "size": [100, 100]}),
        Req("huge-map-3d", "POST", "/maps", V422,
            json={"name": "too-big3", "resolution": 0.01, "origin": [0, 0, 0], "size": [10, 10, 10]}),
        Req("huge-png-scale", "GET", f"/maps/{F}/risk", V422, params={"format": "png", "scale": 100000}),
        Req("deep-json-scans", "POST", f"/maps/{F}/scans", DEEP, content=deep(20000), headers=JSON_CT),
        Req("deep-json-ranges", "POST", f"/maps/{F}/scans", DEEP,
            content=raw_json(scans(laser())).replace('"ranges": [', '"ranges": [' + deep(5000) + ", ", 1),
            headers=JSON_CT),
        Req("deep-json-object", "POST", f"/maps/{F}/scans", DEEP, content=deep(20000, '{"a":', "}"), headers=JSON_CT),
        Req("deep-json-header", "POST", f"/maps/{F}/scans", DEEP,
            content=raw_json(scans(laser(header="__H__"))).replace('"__H__"', deep(3000, '{"a":', "}")[:-3000]
                                                                 + "1" + "}" * 3000), headers=JSON_CT),
        Req("deep-json-map", "POST", "/maps", DEEP, content=deep(20000), headers=JSON_CT),
        Req("deep-json-plan", "POST", f"/maps/{F}/plan", DEEP, content=deep(20000, '{"a":', "}"), headers=JSON_CT),
        Req("deep-json-query", "POST", f"/maps/{F}/risk/query", DEEP,
            content='{"points": ' + deep(20000) + "}", headers=JSON_CT),
    ]


def dimension_cases() -> list[Req]:
    return [
        Req("dims-laser-on-3d", "POST", f"/maps/{C}/scans", V422, json=scans(laser())),
        Req("dims-3d-cloud-on-2d", "POST", f"/maps/{F}/scans", V422, json=scans(cloud())),
        Req("dims-3d-points-2d-pose", "POST", f"/maps/{F}/scans", V422,
            json=scans(cloud(pose={"x": 0, "y": 0, "theta": 0}))),
        Req("dims-2d-points-on-3d", "POST", f"/maps/{C}/scans", V422,
            json=scans(cloud(points=[[1.5, 0.0], [1.5, 0.2]]))),
        Req("dims-ragged-points", "POST", f"/maps/{C}/scans", V422,
            json=scans(cloud(points=[[1.5, 0.0, 0.0], [1.5, 0.2]]))),
        Req("dims-4d-points", "POST", f"/maps/{C}/scans", V422, json=scans(cloud(points=[[1.5, 0.0, 0.0, 1.0]]))),
        Req("dims-quaternion-3", "POST", f"/maps/{C}/scans", V422,
            json=scans(cloud(pose={"position": [0, 0, 1], "orientation": [0, 0, 1]}))),
        Req("dims-quaternion-not-unit", "POST", f"/maps/{C}/scans", V422,
            json=scans(cloud(pose={"position": [0, 0, 1], "orientation": [0, 0, 0, 2]}))),
        Req("dims-position-2", "POST", f"/maps/{C}/scans", V422,
            json=scans(cloud(pose={"position": [0, 0], "orientation": [0, 0, 0, 1]}))),
        Req("dims-ranges-2d-array", "POST", f"/maps/{F}/scans", V422, json=scans(laser(ranges=[[1.0, 2.0]]))),
        Req("dims-ranges-empty", "POST", f"/maps/{F}/scans", V422, json=scans(laser(ranges=[]))),
        Req("dims-no-scans", "POST", f"/maps/{F}/scans", V422, json={"scans": []}),
        Req("dims-scans-not-list", "POST", f"/maps/{F}/scans", V422, json={"scans": {"ranges": [1.0]}}),
        Req("dims-scan-neither", "POST", f"/maps/{F}/scans", V422, json=scans({"pose": {"x": 0, "y": 0, "theta": 0}})),
        Req("dims-range-min-above-max", "POST", f"/maps/{F}/scans", V422, json=scans(laser(range_min=20.0))),
        Req("dims-zero-increment", "POST", f"/maps/{F}/scans", V422, json=scans(laser(angle_increment=0.0))),
        Req("dims-negative-range-max", "POST", f"/maps/{F}/scans", V422, json=scans(laser(range_max=-1.0))),
        Req("dims-unknown-field", "POST", f"/maps/{F}/scans", V422, json=scans(laser(colour="red"))),
        Req("dims-ranges-bad-token", "POST", f"/maps/{F}/scans", V422, json=scans(laser(ranges=[1.0, "far"]))),
        Req("dims-ranges-object", "POST", f"/maps/{F}/scans", V422, json=scans(laser(ranges=[1.0, {"r": 1}]))),
        Req("dims-valid-then-bad", "POST", f"/maps/{F}/scans", V422, json=scans(laser(), laser(), laser(range_max=0))),
        Req("dims-map-origin-size", "POST", "/maps", V422,
            json={"name": "dims1", "resolution": 0.1, "origin": [0, 0], "size": [1, 1, 1]}),
        Req("dims-map-dimensions", "POST", "/maps", V422,
            json={"name": "dims2", "dimensions": 3, "resolution": 0.1, "origin": [0, 0], "size": [1, 1]}),
        Req("dims-map-4d", "POST", "/maps", V422,
            json={"name": "dims3", "resolution": 0.1, "origin": [0, 0, 0, 0], "size": [1, 1, 1, 1]}),
        Req("dims-map-1d", "POST", "/maps", V422, json={"name": "dims4", "resolution": 0.1, "origin": [0], "size": [1]}),
        Req("dims-map-zero-res", "POST", "/maps", V422, json={"name": "dims5", **GOOD_MAP, "resolution": 0}),
        Req("dims-map-negative-size", "POST", "/maps", V422, json={"name": "dims6", **GOOD_MAP, "size": [-1, 1]}),
        Req("dims-map-bad-model", "POST", "/maps", V422, json={"name": "dims7", **GOOD_MAP, "model": "octomap"}),
        Req("dims-plan-3d-start-on-2d", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "start": [0, 0, 0.5]}),
        Req("dims-plan-mixed", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "goal": [1, 0, 0]}),
        Req("dims-plan-1d", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "start": [0]}),
        Req("dims-plan-R3-on-2d", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "state_space": "R3"}),
        Req("dims-plan-space", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "state_space": "R7"}),
        Req("dims-plan-planner", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "planner": "os.system"}),
        Req("dims-plan-time-over-limit", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "time_limit": 1e9}),
        Req("dims-plan-outside", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "start": [1e6, 1e6]}),
        Req("dims-plan-max-risk", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "max_risk": 2}),
        Req("dims-plan-seed", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "seed": -1}),
        Req("dims-plan-seed-huge", "POST", f"/maps/{F}/plan", V422, json={**PLAN, "seed": 2**70}),
        Req("dims-query-3d-on-2d", "POST", f"/maps/{F}/risk/query", V422, json={"points": [[0, 0, 0]]}),
        Req("dims-query-2d-on-3d", "POST", f"/maps/{C}/risk/query", V422, json={"points": [[0, 0]]}),
        Req("dims-query-outside", "POST", f"/maps/{F}/risk/query", V422, json={"points": [[100.0, 0.0]]}),
        Req("dims-query-empty", "POST", f"/maps/{F}/risk/query", V422, json={"points": []}),
        Req("dims-query-strings", "POST", f"/maps/{F}/risk/query", V422, json={"points": [["a", "b"]]}),
        Req("dims-z-band-reversed", "GET", f"/maps/{C}/risk", V422, params={"format": "png", "z_min": 2, "z_max": 1}),
        Req("dims-nav2-thresholds", "GET", f"/maps/{F}/export/nav2", V422,
            params={"free_thresh": 0.9, "occupied_thresh": 0.1}),
        Req("dims-risk-format", "GET", f"/maps/{F}/risk", V422, params={"format": "exe"}),
        Req("dims-binary-cloud-wrong-count", "POST", f"/maps/{C}/scans", V422,
            content=np.ones(10, dtype="<f4").tobytes(), params=CLOUD_QUERY, headers=OCTET),
        Req("dims-binary-npy-3d", "POST", f"/maps/{F}/scans", V422, content=npy(np.ones((2, 2, 2))),
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("dims-binary-npy-points-3-on-2d", "POST", f"/maps/{F}/scans", V422, content=npy(np.ones((5, 3))),
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("dims-binary-quaternion", "POST", f"/maps/{C}/scans", V422,
            content=np.tile([1.5, 0.0, 0.0], (4, 1)).astype("<f4").tobytes(),
            params={**CLOUD_QUERY, "qw": 3.0}, headers=OCTET),
    ]


def name_cases() -> list[Req]:
    bad_names = ["../etc", "..", ".", "-lead", "_x", "a" * 65, "a b", "a/b", "x\u00e9", "a\\b", "a;b", "", " ", "a\nb",
                 "%2e%2e%2fetc", "..%2f..%2fetc"]
    cases = [Req(f"name-create-{i}-{name[:12]!r}", "POST", "/maps", V422, json={"name": name, **GOOD_MAP})
             for i, name in enumerate(bad_names)]
    return cases


# raw paths: sent byte for byte (httpx would resolve dot segments and re-encode)
RAW_PATHS = [
    ("GET", "/maps/..%2Fh-flat"),
    ("GET", "/maps/%2e%2e"),
    ("GET", "/maps/%2E%2E%2F%2E%2E%2Fetc%2Fpasswd"),
    ("GET", "/maps/..%252Fh-flat"),
    ("GET", "/maps/..%5Ch-flat"),
    ("GET", "/maps/h-flat%00"),
    ("GET", "/maps/h-flat%2F..%2Fh-cube"),
    ("DELETE", "/maps/..%2Fh-flat"),
    ("DELETE", "/maps/%2e%2e%2fh-flat"),
    ("DELETE", "/maps/.."),
    ("GET", "/maps/../maps/h-flat"),
    ("DELETE", "/maps/h-cube/../h-flat"),
    ("GET", "/maps/%2e%2e/risk"),
    ("POST", "/maps/..%2Fh-flat/scans"),
    ("POST", "/maps/%2e%2e/plan"),
    ("GET", "/ui/..%2F..%2Fapp%2Fconfig.py"),
    ("GET", "/ui/../../etc/passwd"),
    ("GET", "/ui/%2e%2e%2f%2e%2e%2fetc%2fpasswd"),
    ("GET", "/ui/..%2Fstatic%2Findex.html"),
    ("GET", "/ui/....//....//etc/passwd"),
]


def binary_cases() -> list[Req]:
    ranges = np.full(100, 1.5, dtype="<f4")
    good = npy(ranges)
    header_only = good[:64]
    object_npy = npy(np.array([{"a": 1}, None], dtype=object))
    return [
        Req("binary-truncated-raw", "POST", f"/maps/{F}/scans", V422, content=ranges.tobytes()[:-1],
            params=BINARY_LASER_QUERY, headers=OCTET),
        Req("binary-truncated-npy-data", "POST", f"/maps/{F}/scans", V422, content=good[:-7],
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-truncated-npy-header", "POST", f"/maps/{F}/scans", V422, content=header_only,
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-magic-only", "POST", f"/maps/{F}/scans", V422, content=b"\x93NUMPY",
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-bad-header", "POST", f"/maps/{F}/scans", V422,
            content=b"\x93NUMPY\x01\x00" + struct.pack("<H", 20) + b"{'descr': __import__" + b" " * 10,
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-pickle", "POST", f"/maps/{F}/scans", V422, content=object_npy, params=BINARY_LASER_QUERY,
            headers=NPY),
        Req("binary-npy-int", "POST", f"/maps/{F}/scans", V422, content=npy(np.arange(10)),
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-complex", "POST", f"/maps/{F}/scans", V422, content=npy(np.ones(10, dtype=complex)),
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-float16", "POST", f"/maps/{F}/scans", V422, content=npy(np.ones(10, dtype=np.float16)),
            params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-shape-claims-4GB", "POST", f"/maps/{F}/scans", TOO_BIG,
            content=npy_raw("(1000000000,)", payload=good[128:]), params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-shape-claims-4TB", "POST", f"/maps/{F}/scans", TOO_BIG,
            content=npy_raw("(1000000000000,)", payload=good[128:]), params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-shape-negative", "POST", f"/maps/{F}/scans", V422,
            content=npy_raw("(-1,)", payload=good[128:]), params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-npy-fortran-2d-claim", "POST", f"/maps/{F}/scans", V422,
            content=npy_raw("(10, 10)", payload=good[128:], fortran=True), params=BINARY_LASER_QUERY, headers=NPY),
        Req("binary-empty", "POST", f"/maps/{F}/scans", V422, content=b"", params=BINARY_LASER_QUERY, headers=OCTET),
        Req("binary-missing-query", "POST", f"/maps/{F}/scans", V422, content=ranges.tobytes(), headers=OCTET),
        Req("binary-missing-range-max", "POST", f"/maps/{F}/scans", V422, content=ranges.tobytes(),
            params={k: v for k, v in BINARY_LASER_QUERY.items() if k != "range_max"}, headers=OCTET),
        Req("binary-query-not-number", "POST", f"/maps/{F}/scans", V422, content=ranges.tobytes(),
            params={**BINARY_LASER_QUERY, "x": "one"}, headers=OCTET),
        Req("binary-json-as-octet", "POST", f"/maps/{F}/scans", V422,
            content=json.dumps(scans(laser())).encode(), headers=OCTET),
        Req("binary-cloud-no-pose", "POST", f"/maps/{C}/scans", V422,
            content=np.ones(9, dtype="<f4").tobytes(), headers=OCTET),
    ]


def content_type_cases() -> list[Req]:
    body = json.dumps(scans(laser()))
    return [
        Req("ctype-text-plain", "POST", f"/maps/{F}/scans", frozenset({415}), content=body,
            headers={"content-type": "text/plain"}),
        Req("ctype-form", "POST", f"/maps/{F}/scans", frozenset({415}), content="scans=1",
            headers={"content-type": "application/x-www-form-urlencoded"}),
        Req("ctype-multipart", "POST", f"/maps/{F}/scans", frozenset({415}), content=body,
            headers={"content-type": "multipart/form-data; boundary=x"}),
        Req("ctype-xml", "POST", f"/maps/{F}/scans", frozenset({415}), content="<scans/>",
            headers={"content-type": "application/xml"}),
        Req("ctype-image", "POST", f"/maps/{F}/scans", frozenset({415}), content=b"\x89PNG",
            headers={"content-type": "image/png"}),
        Req("ctype-json-not-json", "POST", f"/maps/{F}/scans", V422, content="scans: [1, 2]", headers=JSON_CT),
        Req("ctype-json-bad-utf8", "POST", f"/maps/{F}/scans", V422, content=b'{"scans": "\xff\xfe"}',
            headers=JSON_CT),
        Req("ctype-json-trailing", "POST", f"/maps/{F}/scans", V422, content=body + "{}", headers=JSON_CT),
        Req("ctype-map-text-plain", "POST", "/maps", frozenset({415, 422}),
            content=json.dumps({"name": "ctype-map", **GOOD_MAP}), headers={"content-type": "text/plain"}),
        Req("ctype-plan-form", "POST", f"/maps/{F}/plan", frozenset({415, 422}), content="start=0",
            headers={"content-type": "application/x-www-form-urlencoded"}),
        Req("ctype-query-xml", "POST", f"/maps/{F}/risk/query", frozenset({415, 422}), content="<points/>",
            headers={"content-type": "application/xml"}),
    ]


def auth_cases() -> list[Req]:
    protected: list[tuple[str, str, Any]] = [
        ("GET", "/maps", None),
        ("POST", "/maps", {"name": "auth-map", **GOOD_MAP}),
        ("GET", f"/maps/{F}", None),
        ("DELETE", f"/maps/{F}", None),
        ("POST", f"/maps/{F}/scans", scans(laser())),
        ("GET", f"/maps/{F}/scans/last", None),
        ("GET", f"/maps/{F}/risk", None),
        ("POST", f"/maps/{F}/risk/query", {"points": [[0.0, 0.0]]}),
        ("GET", f"/maps/{F}/occupancy_grid", None),
        ("GET", f"/maps/{F}/export/nav2", None),
        ("POST", f"/maps/{F}/plan", PLAN),
    ]
    wrong = {
        "missing": {},
        "wrong-key": auth("x" * len(API_KEY)),
        "key-prefix": auth(API_KEY[:-1]),
        "key-suffix": auth(API_KEY + "A"),
        "empty-bearer": {"Authorization": "Bearer"},
        "basic-scheme": {"Authorization": f"Basic {API_KEY}"},
        "key-no-scheme": {"Authorization": API_KEY},
        "key-in-other-header": {"X-API-Key": API_KEY},
    }
    cases = []
    for label, headers in wrong.items():
        for method, path, body in protected:
            cases.append(Req(f"auth-{label}-{method}-{path}", method, path, frozenset({401}), json=body,
                             headers=headers, with_key=False))
    # the binary path checks the key before it reads the body
    cases.append(Req("auth-missing-binary", "POST", f"/maps/{F}/scans", frozenset({401}),
                     content=np.full(100, 1.5, dtype="<f4").tobytes(), params=BINARY_LASER_QUERY, headers=OCTET,
                     with_key=False))
    return cases


CASES: list[Req] = (nonfinite_cases() + size_cases() + dimension_cases() + name_cases() + binary_cases()
                    + content_type_cases() + auth_cases())


def _send(client: httpx.Client, req: Req) -> httpx.Response:
    headers = dict(req.headers)
    if not req.with_key:
        client = httpx.Client(base_url=str(client.base_url), timeout=60.0)
    kwargs: dict[str, Any] = {"params": req.params, "headers": headers}
    if req.json is not None:
        kwargs["json"] = req.json
    elif req.content is not None:
        kwargs["content"] = req.content
    try:
        return client.request(req.method, req.path, **kwargs)
    finally:
        if not req.with_key:
            client.close()


@pytest.mark.parametrize("req", CASES, ids=[c.id for c in CASES])
def test_hostile_request_is_refused_and_changes_nothing(client: httpx.Client, req: Req) -> None:
    before = map_states(client)
    response = _send(client, req)
    SENT["hand-written"] += 1
    assert_refused(response, req.expect)
    assert map_states(client) == before


@pytest.mark.parametrize(("method", "path"), RAW_PATHS, ids=[f"{m}-{p}" for m, p in RAW_PATHS])
def test_traversal_names_reach_no_map_and_no_file(hostile_server: ServerProcess, client: httpx.Client, method: str,
                                                  path: str) -> None:
    before = map_states(client)
    conn = http.client.HTTPConnection("127.0.0.1", hostile_server.port, timeout=30)
    try:
        body = json.dumps(scans(laser())) if method == "POST" else None
        headers = {**auth(), "Content-Type": "application/json"}
        conn.request(method, path, body=body, headers=headers)
        response = conn.getresponse()
        status, data = response.status, response.read()
    finally:
        conn.close()
    SENT["raw-path"] += 1
    assert status in (400, 404, 405, 422), (status, data[:200])
    assert b"root:" not in data and b"FUZZYRISK" not in data  # no file from outside the page was served
    assert map_states(client) == before


def test_body_without_content_length_is_cut_at_the_limit(hostile_server: ServerProcess, client: httpx.Client) -> None:
    """A chunked body (no Content-Length) over the limit: 413 while reading, nothing buffered past it."""
    before = map_states(client)

    def chunks() -> Any:
        chunk = b"[" + b"1.5," * 16384
        for _ in range(MAX_BODY // len(chunk) + 2):
            yield chunk

    response = client.post(f"/maps/{F}/scans", content=chunks(), headers=JSON_CT)
    SENT["hand-written"] += 1
    assert_refused(response, frozenset({413}))
    assert map_states(client) == before


def test_lying_content_length_does_not_hang_or_apply(hostile_server: ServerProcess, client: httpx.Client) -> None:
    """A Content-Length larger than the body sent: the server times the client out or refuses; no map changes."""
    before = map_states(client)
    conn = http.client.HTTPConnection("127.0.0.1", hostile_server.port, timeout=15)
    try:
        conn.putrequest("POST", f"/maps/{F}/scans")
        for key, value in {**auth(), "Content-Type": "application/json", "Content-Length": "100000"}.items():
            conn.putheader(key, value)
        conn.endheaders()
        conn.send(json.dumps(scans(laser())).encode())
        conn.sock.shutdown(1)  # half-close: the rest of the promised body never comes
        try:
            status = conn.getresponse().status
        except (http.client.HTTPException, OSError):
            status = None  # the server dropped the connection: also a refusal
    finally:
        conn.close()
    SENT["raw-path"] += 1
    assert status is None or 400 <= status < 500
    assert map_states(client) == before


def test_valid_requests_still_work_after_the_hostile_ones(client: httpx.Client) -> None:
    """The control: the same server, key and maps accept a good batch (the refusals were not blanket)."""
    before = map_states(client)
    response = client.post(f"/maps/{F}/scans", json=scans(laser()))
    assert response.status_code == 200, response.text
    assert map_states(client)[F] == (before[F][0] + 1, before[F][1] + 1)

