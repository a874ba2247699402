"""The binary ``.npy`` upload reads the header before the data: a lying or broken header is a 4xx, never a 500."""

from __future__ import annotations

import io
import json
import struct
from typing import Any

import numpy as np
from fastapi.testclient import TestClient
from tests.conftest import error_message

NPY = {"Content-Type": "application/x-npy"}
LASER_QUERY = {"x": 0.0, "y": 0.0, "theta": 0.0, "angle_min": -0.7, "angle_increment": 0.01, "range_min": 0.05,
               "range_max": 10.0}


def _npy_v1(header: str, payload: bytes) -> bytes:
    """A version 1.0 ``.npy`` with exactly this header text, padded as numpy pads it."""
    total = 10 + len(header) + 1
    text = header + " " * ((64 - total % 64) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode("latin1") + payload


def _claim(shape: str, payload: bytes, descr: str = "<f4", fortran: bool = False) -> bytes:
    return _npy_v1(f"{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}", payload)


def _post(client: TestClient, content: bytes) -> Any:
    return client.post("/maps/lab/scans", params=LASER_QUERY, content=content, headers=NPY)


def _unchanged(client: TestClient, kit: Any, before: np.ndarray) -> bool:
    return kit.version(client, "lab") == 0 and np.array_equal(kit.risk_npy(client, "lab"), before)


def test_a_header_that_does_not_tokenize_answers_422_and_changes_nothing(lab: TestClient, kit: Any) -> None:
    before = kit.risk_npy(lab, "lab")
    # numpy's header reader raises tokenize.TokenError on this one (an unclosed bracket)
    body = b"\x93NUMPY\x01\x00" + struct.pack("<H", 20) + b"{'descr': __import__" + b" " * 10
    response = _post(lab, body)
    assert response.status_code == 422, response.text
    assert ".npy header" in error_message(response) and "numpy.save" in error_message(response)
    assert _unchanged(lab, kit, before)


def test_a_header_claiming_a_trillion_beams_answers_413_without_allocating(lab: TestClient, kit: Any) -> None:
    before = kit.risk_npy(lab, "lab")
    response = _post(lab, _claim("(1000000000000,)", np.full(100, 1.5, "<f4").tobytes()))
    assert response.status_code == 413, response.text
    detail = error_message(response)
    assert "1000000000000" in detail and "FUZZYRISK_MAX_RAYS_PER_SCAN" in detail
    assert _unchanged(lab, kit, before)


def test_a_shape_that_does_not_match_the_bytes_sent_answers_422(lab: TestClient, kit: Any) -> None:
    before = kit.risk_npy(lab, "lab")
    ranges = np.full(100, 1.5, "<f4").tobytes()
    for body, needle in ((_claim("(100,)", ranges[:-8]), "392 bytes"), (_claim("(100,)", ranges + b"\0" * 4), "404"),
                         (_claim("(-1,)", ranges), "negative")):
        response = _post(lab, body)
        assert response.status_code == 422, response.text
        assert needle in error_message(response)
    assert _unchanged(lab, kit, before)


def test_big_endian_and_integer_arrays_are_refused_with_what_to_send(lab: TestClient, kit: Any) -> None:
    ranges = np.full(100, 1.5)
    for array, needle in ((ranges.astype(">f4"), "little-endian"), (ranges.astype("<i4"), "float32 or float64")):
        out = io.BytesIO()
        np.save(out, array)
        response = _post(lab, out.getvalue())
        assert response.status_code == 422, response.text
        assert needle in json.dumps(response.json())


def test_a_fortran_order_npy_fuses_like_the_same_points_in_c_order(client: TestClient, kit: Any) -> None:
    points = kit.cloud_sensor_points(150)
    pose = {"x": 0.5, "y": -0.5, "z": 1.0, "qz": 0.0, "qw": 1.0, "range_max": 10.0}
    for name, array in (("c_order", np.ascontiguousarray(points)), ("f_order", np.asfortranarray(points))):
        client.post("/maps", json={**kit.MAP_3D, "name": name})
        response = client.post(f"/maps/{name}/scans", params=pose, content=kit.npy(array), headers=NPY)
        assert response.status_code == 200, response.text
    assert np.array_equal(kit.risk_npy(client, "f_order"), kit.risk_npy(client, "c_order"))
