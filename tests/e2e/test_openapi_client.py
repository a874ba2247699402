"""A client generated from the service's OpenAPI document by openapi-python-client drives every operation:
the document is one a generator can use, and what the generated code sends and parses
is what the service answers.

The client is generated from the live server's ``/openapi.json``, as a user would, into a temporary
directory, and imported from there. Every operation of the document must have been generated (a new
route that a generator cannot use fails here) and is called at least once below.
"""

from __future__ import annotations

import importlib
import io
import json
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from types import ModuleType
from typing import Any

import httpx
import numpy as np
import pytest
from mcap.reader import make_reader
from PIL import Image
from rosbags.typesys import Stores, get_typestore

from tests.e2e.conftest import BEAMS, POSES, RANGE_MAX, WORLD_MAP, Server, laser_json, scan_ranges

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

KEY = "generated-client-key-0123456789"


def jazzy_typestore() -> Any:
    return get_typestore(Stores.ROS2_JAZZY)
PACKAGE = "fuzzyrisk_client"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    started = Server(tmp_path_factory.mktemp("openapi-client") / "data", env={"FUZZYRISK_API_KEY": KEY}).start()
    yield started
    started.stop()


@pytest.fixture(scope="module")
def generated(server: Server, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ModuleType, dict[str, Any]]]:
    """The generated package, imported from a temporary directory, and the document it was made from."""
    out = tmp_path_factory.mktemp("generated")
    document = httpx.get(f"{server.url}/openapi.json", timeout=30).json()
    (out / "openapi.json").write_text(json.dumps(document))
    (out / "config.yaml").write_text("post_hooks: []\n")  # no formatter run: nothing here reads the style
    run = subprocess.run(
        [sys.executable, "-m", "openapi_python_client", "generate", "--path", str(out / "openapi.json"),
         "--config", str(out / "config.yaml"), "--meta", "none", "--output-path", str(out / PACKAGE)],
        capture_output=True, text=True, timeout=300, cwd=out,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    # a warning may name a request media type the generator has no encoder for (application/x-npy) when
    # the same body is also declared as application/octet-stream; nothing else may be left out
    report = run.stdout + run.stderr
    assert "response will be omitted" not in report, report
    assert "Unable to parse" not in report and "Skipping" not in report.replace("Skipping Integration", ""), report
    sys.path.insert(0, str(out))
    try:
        yield importlib.import_module(PACKAGE), document
    finally:
        sys.path.remove(str(out))
        for name in [m for m in sys.modules if m == PACKAGE or m.startswith(PACKAGE + ".")]:
            del sys.modules[name]


def _op(package: ModuleType, tag: str, operation_id: str) -> Any:
    return importlib.import_module(f"{package.__name__}.api.{tag}.{operation_id}")


def _models(package: ModuleType) -> Any:
    return importlib.import_module(f"{package.__name__}.models")


def test_the_generated_client_drives_every_operation(generated: tuple[ModuleType, dict[str, Any]],
                                                     server: Server) -> None:
    package, document = generated
    m = _models(package)
    client = package.AuthenticatedClient(base_url=server.url, token=KEY, timeout=httpx.Timeout(120.0))
    called: set[str] = set()

    def op(tag: str, operation_id: str) -> Any:
        called.add(operation_id)
        return _op(package, tag, operation_id)

    # probes (no key needed, but an authenticated client may call them too)
    assert op("operations", "health").sync(client=client).status == "ok"
    assert op("operations", "ready").sync(client=client).status == "ready"
    metrics = op("operations", "metrics").sync_detailed(client=client)
    assert metrics.status_code == 200 and b"fuzzyrisk_" in metrics.content

    # maps
    info = op("maps", "create_map").sync(client=client, body=m.MapCreate.from_dict(WORLD_MAP))
    assert isinstance(info, m.MapInfo) and info.name == "hall" and info.version == 0
    taken = op("maps", "create_map").sync(client=client, body=m.MapCreate.from_dict(WORLD_MAP))
    assert isinstance(taken, m.ErrorBody) and taken.code == "CONFLICT" and "hall" in taken.message
    assert [x.name for x in op("maps", "list_maps").sync(client=client)] == ["hall"]
    missing = op("maps", "get_map").sync("nope", client=client)
    assert isinstance(missing, m.ErrorBody) and missing.code == "NOT_FOUND"
    # a map's settings copied with the generated models: what GET shows, POST takes (the engine object included)
    facts = {key for key, field in document["components"]["schemas"]["MapInfo"]["properties"].items()
             if field.get("readOnly")}
    settings = {key: value for key, value in info.to_dict().items() if key not in facts}
    copy = op("maps", "create_map").sync(client=client, body=m.MapCreate.from_dict({**settings, "name": "hall-copy"}))
    assert isinstance(copy, m.MapInfo), copy
    shown = op("maps", "get_map").sync("hall-copy", client=client).to_dict()
    assert {key: value for key, value in shown.items() if key not in facts} == {**settings, "name": "hall-copy"}
    assert op("maps", "delete_map").sync_detailed("hall-copy", client=client).status_code == 204

    # scans: JSON batches (no-returns as the "inf" token), then one binary scan (raw float32 + query)
    batch = m.ScanBatch.from_dict({"scans": [laser_json(pose) for pose in POSES[:-1]]})
    fused = op("scans", "post_scans").sync("hall", client=client, body=batch)
    assert isinstance(fused, m.BatchResult) and fused.scans_fused == len(POSES) - 1
    x, y, theta = POSES[-1]
    raw = scan_ranges(x, y, theta).astype("<f4").tobytes()
    body = package.types.File(payload=io.BytesIO(raw), mime_type="application/octet-stream")
    one = op("scans", "post_scans").sync(
        "hall", client=client, body=body, x=x, y=y, theta=theta, angle_min=-np.pi, angle_increment=2 * np.pi / BEAMS,
        range_min=0.05, range_max=RANGE_MAX,
    )
    assert isinstance(one, m.BatchResult) and one.version == fused.version + 1
    assert op("maps", "get_map").sync("hall", client=client).scans_fused == len(POSES)
    last = op("scans", "last_scan").sync("hall", client=client)
    assert isinstance(last, m.LastScan) and last.version == one.version
    # a bag upload (real bags: tests/app/cli/test_import_bag.py): bytes that are no bag answer the one error body
    not_a_bag = package.types.File(payload=io.BytesIO(b"not a bag"), mime_type="application/octet-stream")
    refused_bag = op("scans", "post_bag").sync("hall", client=client, body=not_a_bag)
    assert isinstance(refused_bag, m.ErrorBody) and refused_bag.code == "INVALID" and "bag" in refused_bag.message

    # risk, in every format, all the same numbers
    grid = op("risk", "get_risk").sync("hall", client=client)
    assert isinstance(grid, m.RiskGridJSON)
    risk = np.asarray(grid.risk, dtype=np.float64)
    npy = op("risk", "get_risk_npy").sync("hall", client=client)
    from_npy = np.load(io.BytesIO(npy.payload.read()), allow_pickle=False)
    np.testing.assert_array_equal(np.round(from_npy.astype(np.float64), 6), risk)  # JSON: rounded to 1e-6
    observed = op("risk", "get_risk_npy").sync("hall", client=client, layer=m.GetRiskNpyLayer.OBSERVED)
    assert np.load(io.BytesIO(observed.payload.read())).dtype == bool
    png = op("risk", "get_risk_png").sync("hall", client=client, scale=2)
    assert Image.open(io.BytesIO(png.payload.read())).size == (2 * risk.shape[0], 2 * risk.shape[1])
    values = op("risk", "query_risk").sync("hall", client=client, body=m.RiskQuery.from_dict({"points": [[5.0, 3.0]]}))
    assert isinstance(values, m.RiskValues) and values.risk[0] == pytest.approx(float(from_npy[100, 60]), abs=0)
    ogrid = op("risk", "occupancy_grid").sync("hall", client=client)
    assert isinstance(ogrid, m.OccupancyGrid) and ogrid.info.width == risk.shape[0]
    # the OccupancyGrid as ROS 2 bytes: what a ROS 2 node deserializes equals the JSON message
    cdr = op("risk", "occupancy_grid_file").sync("hall", m.OccupancyGridFileEncoding.CDR, client=client).payload.read()
    message = jazzy_typestore().deserialize_cdr(cdr, "nav_msgs/msg/OccupancyGrid")
    assert message.header.frame_id == ogrid.header.frame_id == "map"
    assert (message.info.width, message.info.height) == (ogrid.info.width, ogrid.info.height)
    assert message.data.tolist() == ogrid.data
    mcap_bytes = op("risk", "occupancy_grid_file").sync("hall", m.OccupancyGridFileEncoding.MCAP,
                                                        client=client).payload.read()
    (entry,) = list(make_reader(io.BytesIO(mcap_bytes)).iter_messages())
    assert entry[1].topic == "/map" and entry[2].data == cdr
    nav2 = op("risk", "export_nav2").sync("hall", client=client, mode=m.ExportNav2Mode.TRINARY).payload.read()
    assert {"map.yaml", "map.pgm"} <= set(zipfile.ZipFile(io.BytesIO(nav2)).namelist())
    # the export back in as a new map, its two files as a form (the generator's form of the operation's bodies):
    # its first batch, the same grid
    with zipfile.ZipFile(io.BytesIO(nav2)) as files:
        saved = m.ImportMapFilesBody(
            yaml=package.types.File(payload=io.BytesIO(files.read("map.yaml")), file_name="map.yaml"),
            image=package.types.File(payload=io.BytesIO(files.read("map.pgm")), file_name="map.pgm"))
    copy = op("maps", "import_map").sync(client=client, body=saved, name="hall_copy")
    assert isinstance(copy, m.MapInfo) and copy.version == 1 and copy.shape == [risk.shape[0], risk.shape[1]]
    again = op("risk", "export_nav2").sync("hall_copy", client=client, mode=m.ExportNav2Mode.TRINARY).payload.read()
    assert zipfile.ZipFile(io.BytesIO(again)).read("map.pgm") == zipfile.ZipFile(io.BytesIO(nav2)).read("map.pgm")
    assert op("maps", "delete_map").sync_detailed("hall_copy", client=client).status_code == 204
    # the recording for offline viewing: the same grid on /map, every scan on /scan (no snapshot yet), the
    # binary scan's float32 ranges as sent
    recorded = op("recordings", "export_mcap").sync("hall", client=client).payload.read()
    messages = [(c.topic, msg.data)
                for _, c, msg in make_reader(io.BytesIO(recorded)).iter_messages(log_time_order=True)]
    assert [d for t, d in messages if t == "/map"] == [cdr]
    scans = [d for t, d in messages if t == "/scan"]
    assert len(scans) == len(POSES) and [t for t, _ in messages].count("/tf") == len(POSES)
    last_scan = jazzy_typestore().deserialize_cdr(scans[-1], "sensor_msgs/msg/LaserScan")
    assert last_scan.ranges.astype("<f4").tobytes() == raw

    # the trajectory: every scan's sensor pose as posted, in order, stamped when the service received it
    path = op("trajectory", "get_trajectory").sync("hall", client=client)
    assert isinstance(path, m.Trajectory) and path.version == one.version and path.unstamped == 0
    assert [(p.pose.position.x, p.pose.position.y) for p in path.poses] == [(px, py) for px, py, _ in POSES]
    assert all(p.header.stamp.sec > 0 and p.header.frame_id == "map" for p in path.poses)

    # plans, a start the planner cannot use (Nav2's code in the one error body), and a path checked
    names = [p.name for p in op("plans", "planners").sync(client=client).planners]
    assert "grid" in names and "RRTstar" in names
    request = {"start": [1.5, 1.5], "goal": [8.5, 4.5], "planner": "grid", "time_limit": 5.0}
    result = op("plans", "plan").sync("hall", client=client, body=m.PlanRequest.from_dict(request))
    assert isinstance(result, m.PlanResult) and result.status == "exact" and len(result.path) >= 2
    outside = op("plans", "plan").sync("hall", client=client,
                                       body=m.PlanRequest.from_dict({**request, "start": [-1.0, 1.0]}))
    assert isinstance(outside, m.ErrorBody) and outside.code == "START_OUTSIDE_MAP"
    # the plan's own nav_msgs/Path, checked on its version, as the generated models carry it
    check = m.PathCheckRequest.from_dict({"poses": [p.to_dict() for p in result.poses],
                                          "header": result.header.to_dict()})
    checked = op("plans", "check_path").sync("hall", client=client, body=check)
    assert isinstance(checked, m.PathCheckResult) and checked.valid and checked.version == result.version
    assert checked.cost == result.cost

    # a growing map's setting changed, and a region cleared, through the generated models
    grown = op("maps", "create_map").sync(client=client, body=m.MapCreate.from_dict({"name": "roam", "resolution": 0.1}))
    assert isinstance(grown, m.MapInfo) and grown.extent == "growing" and grown.bounds is None
    changed = op("maps", "change_map").sync("roam", client=client, body=m.MapChange.from_dict({"forget_beyond": 25.0}))
    assert isinstance(changed, m.MapInfo) and changed.forget_beyond == 25.0 and changed.version == 1
    cleared = op("maps", "clear_region").sync("hall", client=client,
                                              body=m.ClearRegion.from_dict({"min": [4.0, 0.0], "max": [6.0, 6.0]}))
    assert isinstance(cleared, m.Cleared) and cleared.cells_cleared > 0
    assert op("maps", "delete_map").sync_detailed("roam", client=client).status_code == 204

    # a correction (the first pose moved; the scans of a batch posted without stamps share the time it arrived):
    # the map rebuilt in the background, one version on
    before = op("maps", "get_map").sync("hall", client=client)
    moved = path.poses[0].to_dict()
    moved["pose"]["position"]["x"] += 0.05
    corrected = m.CorrectedPath.from_dict({"header": path.header.to_dict(), "poses": [moved]})
    accepted = op("trajectory", "put_trajectory").sync("hall", client=client, body=corrected)
    assert isinstance(accepted, m.RebuildAccepted) and accepted.rebuild.scans_reposed >= 1
    deadline = time.monotonic() + 60
    while (status := op("trajectory", "get_rebuild").sync("hall", client=client)).state != "done":
        assert status.state == "running" and time.monotonic() < deadline, status
        time.sleep(0.05)
    assert status.id == accepted.rebuild.id and status.version == before.version + 1

    # the key, and a deletion
    anonymous = package.Client(base_url=server.url)
    refused = _op(package, "maps", "list_maps").sync_detailed(client=anonymous)
    assert refused.status_code == 401 and isinstance(refused.parsed, m.ErrorBody)
    assert refused.parsed.code == "UNAUTHORIZED"
    assert op("maps", "delete_map").sync_detailed("hall", client=client).status_code == 204
    gone = _op(package, "maps", "get_map").sync("hall", client=client)
    assert isinstance(gone, m.ErrorBody) and gone.code == "NOT_FOUND"

    every = {o["operationId"] for item in document["paths"].values() for o in item.values()}
    assert called == every, f"operations no test drove: {sorted(every - called)}"
