"""Write ``tests/data/stored_log/``: a service's store and the maps it held, for replay tests across code changes.

Run once, from the repository's root, with the code whose maps are to be kept::

    PYTHONPATH=$PWD python tests/data/stored_log/make_store.py

It posts ``REQUESTS`` (2-D and 3-D maps; JSON, ``.npy``, CDR and bag bodies; sensor poses with tilted,
upside-down and not quite unit quaternions) to the service in-process, then writes beside this file:

- ``requests.json.gz``: every request as sent (binary bodies in base64), in order, with the maps created first;
- ``fuzzyrisk.sqlite3``: the service's store, copied by ``app.storage.backup`` while the service ran, so that
  each map keeps the batches after its last snapshot in its log (a clean stop would snapshot them);
- ``maps.npz``: each map's ``to_arrays()`` and its risk as ``GET /maps/{name}/risk.npy`` serves it, keys
  ``<map>.<array>``;
- ``batches.npz``: every batch record the service logged (its scans in the map frame, ``app.maps.logcodec``),
  from a second run that takes no snapshot, keys ``<map>.<version>``.

``tests/app/maps/test_stored.py`` replays the store and re-posts the requests with today's code and
compares both with ``maps.npz``, bit for bit. Never re-run this to make that test pass: the files hold the
maps of the code they were written with (``tests/data/README.md``).
"""

from __future__ import annotations

import base64
import gzip
import io
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

from app.api.factory import create_app
from app.config import Settings
from app.storage.backup import DATABASE, backup
from tests.app._ros import CLOUD_CT, LASER_CT, cdr, cloud_msg, laser_msg, store, wall_ranges
from tests.app.cli.test_import_bag import cloud_scenario, laser_scenario, write_bag
from tests.app.maps.test_stored import NEVER, SNAPSHOT_EVERY, held_arrays, logged_batches, send

HERE = Path(__file__).resolve().parent
MAPS: list[dict[str, Any]] = [
    {"name": "flat", "dimensions": 2, "resolution": 0.1, "origin": [-6.0, -6.0], "size": [12.0, 12.0]},
    {"name": "hall", "dimensions": 3, "resolution": 0.2, "origin": [-4.0, -4.0, -1.0], "size": [8.0, 8.0, 4.0]},
    {"name": "bayes", "dimensions": 3, "resolution": 0.2, "origin": [-4.0, -4.0, -1.0], "size": [8.0, 8.0, 4.0],
     "model": "bayes"},
]


def _unit(q: Any) -> list[float]:
    q = np.asarray(q, dtype=np.float64)
    return (q / np.linalg.norm(q)).tolist()


#: Sensor orientations [qx, qy, qz, qw]: tilted in every axis, rolled upside down, one not quite unit.
TILTED = _unit([0.11, -0.23, 0.41, 0.87])
ROLLED = _unit([0.97, 0.05, -0.2, 0.08])  # about pi around x: upside down, turned
PITCHED = _unit([-0.05, 0.31, -0.6, 0.73])
NEAR_UNIT = (np.array(_unit([0.3, 0.2, -0.1, 0.92])) * (1.0 + 4e-4)).tolist()  # norm 1.0004: normalised inside
LEVEL_DOWN = _unit([0.0, 1.0, 0.0, 0.0])  # level LaserScan, mounted upside down (z down)


def _near_unit(rng: np.random.Generator) -> list[float]:
    """A random orientation whose norm is off 1 by up to 9e-4 (a pose may be off by 1e-3)."""
    return (np.array(_unit(rng.normal(size=4))) * (1.0 + rng.uniform(-9e-4, 9e-4))).tolist()


def _pose_query(position: list[float], quaternion: list[float], **extra: Any) -> dict[str, Any]:
    return {**dict(zip(("x", "y", "z", "qx", "qy", "qz", "qw"), [*position, *quaternion])), **extra}


def _cloud_points(rng: np.random.Generator, n: int, dims: int = 3) -> np.ndarray:
    """Sensor-frame points of a room seen from inside: walls 1.5 to 3.5 m away in any direction."""
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    points = directions * rng.uniform(1.5, 3.5, size=(n, 1))
    return points[:, :dims]


def _json_cloud(pose: dict[str, Any], points: np.ndarray, range_max: float) -> dict[str, Any]:
    return {"pose": pose, "points": points.tolist(), "range_max": range_max}


def _laser(theta: float, x: float, y: float, rng: np.random.Generator) -> dict[str, Any]:
    n = 181
    ranges = rng.uniform(1.0, 5.0, n)
    ranges[rng.choice(n, 8, replace=False)] = np.inf
    return {"pose": {"x": x, "y": y, "theta": theta}, "angle_min": -np.pi / 2, "angle_increment": np.pi / (n - 1),
            "ranges": ["inf" if np.isinf(r) else float(r) for r in ranges], "range_min": 0.1, "range_max": 6.0}


def _npy(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.save(out, array)
    return out.getvalue()


def requests(work: Path) -> list[dict[str, Any]]:
    """Every request, in the order it is sent: ``{map, kind, content_type, params, json | base64}``."""
    rng = np.random.default_rng(31)
    ts = store("jazzy")
    out: list[dict[str, Any]] = []

    def scans(name: str, content_type: str, *, body: bytes | None = None, json_body: Any = None,
              kind: str = "scans", **params: Any) -> None:
        item: dict[str, Any] = {"map": name, "kind": kind, "content_type": content_type, "params": params}
        if json_body is not None:
            item["json"] = json_body
        else:
            item["base64"] = base64.b64encode(body or b"").decode("ascii")
        out.append(item)

    def cloud_cdr(n: int) -> bytes:
        return cdr(ts, cloud_msg(ts, _cloud_points(rng, n).astype(np.float32).astype(np.float64)))

    # 2-D map "flat": planar scans, PointCloud2 bodies rotated into the map's plane, a level LaserScan body
    scans("flat", "application/json", json_body={"scans": [_laser(t, x, y, rng) for t, x, y in
                                                           ((0.0, 0.0, 0.0), (1.3, 0.5, -0.4), (-2.6, -1.0, 1.2))]})
    scans("flat", CLOUD_CT, body=cloud_cdr(400), **_pose_query([0.2, -0.3, 0.4], TILTED, range_max=5.0))
    scans("flat", CLOUD_CT, body=cloud_cdr(400), **_pose_query([-0.7, 0.9, 1.1], ROLLED, range_max=5.0))
    ranges = wall_ranges(n=121, wall=2.2, seed=4)
    scans("flat", LASER_CT, body=cdr(ts, laser_msg(ts, ranges)), **_pose_query([0.4, 0.1, 0.2], LEVEL_DOWN))
    scans("flat", "application/json", json_body={"scans": [_json_cloud(
        {"x": 0.3, "y": -0.2, "theta": 0.77}, _cloud_points(rng, 300, dims=2), 5.0)]})
    bag = write_bag(laser_scenario(), work / "drive2d", "mcap-jazzy")
    scans("flat", "application/x-mcap", body=bag.read_bytes(), kind="bags")
    scans("flat", CLOUD_CT, body=cloud_cdr(300), **_pose_query([1.0, 1.0, 0.3], NEAR_UNIT, range_max=5.0))
    for _ in range(4):  # any orientation, norms within the 1e-3 a pose may be off: normalised to varied last bits
        scans("flat", CLOUD_CT, body=cloud_cdr(100), **_pose_query(rng.uniform(-1.0, 1.0, 3).tolist(),
                                                                   _near_unit(rng), range_max=5.0))

    # 3-D map "hall": clouds with 3-D poses as JSON, .npy and CDR bodies, a tilted LaserScan, a bag placed by TF
    scans("hall", "application/json", json_body={"scans": [
        _json_cloud({"position": [0.1, 0.2, 1.0], "orientation": TILTED}, _cloud_points(rng, 500), 4.0),
        _json_cloud({"position": [-0.5, 0.3, 1.2], "orientation": NEAR_UNIT}, _cloud_points(rng, 500), 4.0)]})
    scans("hall", "application/x-npy", body=_npy(_cloud_points(rng, 400)),
          **_pose_query([0.6, -0.4, 0.9], PITCHED, range_max=4.0))
    scans("hall", CLOUD_CT, body=cloud_cdr(400), **_pose_query([-0.2, -0.6, 1.5], ROLLED, range_max=4.0))
    scans("hall", LASER_CT, body=cdr(ts, laser_msg(ts, wall_ranges(n=121, wall=2.0, seed=6), range_max=3.5)),
          **_pose_query([0.0, 0.5, 0.8], PITCHED))
    bag = write_bag(cloud_scenario(), work / "drive3d", "mcap-jazzy")
    scans("hall", "application/x-mcap", body=bag.read_bytes(), kind="bags")
    scans("hall", "application/json", json_body={"scans": [
        _json_cloud({"position": [0.4, 0.4, 0.6], "orientation": PITCHED}, _cloud_points(rng, 500), 4.0)]})
    scans("hall", "application/json", json_body={"scans": [
        _json_cloud({"position": rng.uniform(-1.0, 1.0, 3).tolist(), "orientation": _near_unit(rng)},
                    _cloud_points(rng, 60), 4.0) for _ in range(16)]})

    # 3-D Bayes map "bayes": float32 log-odds, as sensitive to a point's last bit as any
    scans("bayes", "application/json", json_body={"scans": [
        _json_cloud({"position": [0.0, 0.0, 1.0], "orientation": ROLLED}, _cloud_points(rng, 500), 4.0)]})
    scans("bayes", CLOUD_CT, body=cloud_cdr(400), **_pose_query([0.3, -0.3, 0.7], TILTED, range_max=4.0))
    return out


def settings(data_dir: Path, snapshot_every: int) -> Settings:
    return Settings(data_dir=data_dir, plan_warmup=False, plan_workers=1, disk_reserve_bytes=64 * 1024,
                    snapshot_every=snapshot_every)


def run(data_dir: Path, sent: list[dict[str, Any]], snapshot_every: int) -> TestClient:
    """A service on ``data_dir`` (entered: the caller exits it) that created the maps and was sent ``sent``."""
    client = TestClient(create_app(settings(data_dir, snapshot_every)))
    client.__enter__()
    wait_ready(client)
    for spec in MAPS:
        assert client.post("/maps", json=spec).status_code == 201
    for item in sent:
        response = send(client, item)
        assert response.status_code == 200, response.text
    return client


def wait_ready(client: TestClient) -> None:
    deadline = time.monotonic() + 300
    while client.get("/ready").json()["status"] == "starting":
        assert time.monotonic() < deadline, "the service was not ready in 300 s"
        time.sleep(0.05)


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        sent = requests(work)
        client = run(work / "service", sent, SNAPSHOT_EVERY)
        try:
            writes = client.app.state.service.writes  # type: ignore[attr-defined]
            while writes.snapshots_being_written:
                time.sleep(0.01)
            maps = {spec["name"]: held_arrays(client, spec["name"]) for spec in MAPS}
            (HERE / DATABASE).unlink(missing_ok=True)
            backup(work / "service", HERE / DATABASE)
        finally:
            client.__exit__(None, None, None)
        client = run(work / "logged", sent, NEVER)
        try:
            logged = {spec["name"]: logged_batches(client, spec["name"]) for spec in MAPS}
            for spec in MAPS:  # snapshots or not, the same maps
                again = held_arrays(client, spec["name"])
                assert all(again[k].tobytes() == v.tobytes() for k, v in maps[spec["name"]].items())
        finally:
            client.__exit__(None, None, None)
        np.savez_compressed(HERE / "maps.npz", **{f"{name}.{key}": value for name, arrays in maps.items()
                                                  for key, value in arrays.items()})
        np.savez_compressed(HERE / "batches.npz", **{f"{name}.{version}": np.frombuffer(payload, np.uint8)
                                                     for name, batches in logged.items()
                                                     for version, payload in batches.items()})
        with gzip.GzipFile(HERE / "requests.json.gz", "wb", mtime=0) as out:
            out.write(json.dumps({"maps": MAPS, "requests": sent}, indent=1).encode() + b"\n")
    for path in sorted(HERE.iterdir()):
        print(f"{path.name}: {path.stat().st_size:,} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
