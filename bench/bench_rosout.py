"""OccupancyGrid of a 4M-cell map as CDR and MCAP against the JSON OccupancyGrid (CDR <= 150 ms).

Run: ``python3 dev.py bench rosout`` (or ``.venv/bin/python -m bench.bench_rosout [--runs N]``).

One service in this process (the app with its lifespan, on a temporary data directory), a map of
2000 x 2000 cells of 0.05 m with 64 scans of a room fused. Each format is timed twice:
*server-side* is ``MapReads.occupancy_grid`` on the service's event loop (grid copy, projection to
int8, message building and encoding: what the route awaits), *HTTP* is ``GET
/maps/{name}/occupancy_grid`` through the in-process test client (adds routing and the transfer of
the body through httpx). Medians of ``--runs`` runs (3 for JSON, which takes seconds).
"""

from __future__ import annotations

import argparse
import functools
import math
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

from app.config import Settings
from app.api.factory import create_app

SIDE_CELLS = 2000
RESOLUTION_M = 0.05
SCANS = 64


def _room_scans() -> list[dict[str, Any]]:
    """LaserScans (720 beams over 360 degrees) of a 90 m x 90 m room from a grid of poses."""
    half = 0.45 * SIDE_CELLS * RESOLUTION_M
    angles = -math.pi + np.arange(720) * (2 * math.pi / 720)
    scans = []
    for k in range(SCANS):
        x, y = (k % 8 - 3.5) * 10.0, (k // 8 - 3.5) * 10.0
        with np.errstate(divide="ignore"):
            tx = np.where(np.cos(angles) > 0, half - x, -half - x) / np.cos(angles)
            ty = np.where(np.sin(angles) > 0, half - y, -half - y) / np.sin(angles)
        ranges = np.minimum(np.abs(tx), np.abs(ty))
        scans.append({"pose": {"x": x, "y": y, "theta": 0.0}, "angle_min": -math.pi,
                      "angle_increment": 2 * math.pi / 720, "ranges": np.round(ranges, 4).tolist(),
                      "range_min": 0.1, "range_max": 60.0})
    return scans


def _median_s(fn: Callable[[], Any], runs: int) -> tuple[float, Any]:
    times, result = [], None
    for _ in range(runs):
        started = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - started)
    return statistics.median(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help="runs per format (JSON: at most 3)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), plan_warmup=False, plan_workers=1)
        with TestClient(create_app(settings)) as client:
            side_m = SIDE_CELLS * RESOLUTION_M
            client.post("/maps", json={"name": "big", "resolution": RESOLUTION_M, "origin": [-side_m / 2] * 2,
                                       "size": [side_m, side_m]}).raise_for_status()
            scans = _room_scans()
            for start in range(0, SCANS, 16):
                client.post("/maps/big/scans", json={"scans": scans[start:start + 16]}).raise_for_status()
            service = client.app.state.service  # type: ignore[attr-defined]
            print(f"bench rosout: OccupancyGrid (trinary) of a {SIDE_CELLS} x {SIDE_CELLS} map "
                  f"({SIDE_CELLS * SIDE_CELLS / 1e6:.0f}M cells, {SCANS} scans fused), median of runs")
            print(f"{'format':<6} {'server-side ms':>15} {'HTTP ms':>9} {'bytes':>12}")
            assert client.portal is not None  # set while the client is open
            read_s, _ = _median_s(functools.partial(client.portal.call, service.reads.read_grid, "big"), args.runs)
            print(f"{'(read)':<6} {read_s * 1e3:>15.1f} {'':>9} {'':>12}   the grid read every format starts with")
            for encoding in ("cdr", "mcap", "json"):
                runs = min(args.runs, 3) if encoding == "json" else args.runs
                call = functools.partial(service.reads.occupancy_grid, "big", mode="trinary", free_thresh=0.45,
                                         occupied_thresh=0.6, z_min=None, z_max=None, encoding=encoding)
                portal = client.portal
                assert portal is not None  # set while the client is open
                def read(call: functools.partial[Any] = call) -> Any:
                    message, _, sent = portal.call(call)
                    if sent is not None:
                        sent()  # a big read holds the read lane until its body is sent: here, once it is made
                    return message

                read()  # warm: the typestore and the serializer are built once
                server_s, message = _median_s(read, runs)
                body = message if isinstance(message, bytes) else b"".join(message)  # CDR as sent: head, cells
                http_s, response = _median_s(
                    functools.partial(client.get, "/maps/big/occupancy_grid", params={"format": encoding}), runs)
                assert response.status_code == 200 and response.content == body
                print(f"{encoding:<6} {server_s * 1e3:>15.1f} {http_s * 1e3:>9.1f} {len(body):>12,}")


if __name__ == "__main__":
    main()
