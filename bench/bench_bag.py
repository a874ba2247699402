"""Bag import speed: scans/s of ``python -m app.import_bag`` and of ``POST /maps/{name}/bags``.

Run: ``.venv/bin/python -m bench.bench_bag [--scans 1000] [--beams 720]``.

A rosbag2 (mcap) of a robot driving through a 20 m x 20 m room is written first with rosbags:
``--scans`` LaserScans (``--beams`` beams over 360 degrees, 10 Hz, a few NaN/inf readings), ``/tf`` with
map -> odom at 1 Hz and odom -> base_link at 50 Hz, ``/tf_static`` base_link -> laser. Then, best of
``--runs``: the import in-process, split into reading (TF buffer, deserialization, interpolated
poses, conversion: ``read_bag``) and fusion, at 0.05 m on a map of the data's bounds; and the same
bag uploaded to a service in this process (TestClient, its lifespan included). Numba's compilation
is excluded (a warm-up fusion first).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient
from rosbags.rosbag2 import StoragePlugin, Writer

from app.ros import bags
from app.config import Settings
from app.api.factory import create_app
from app.formats.mediatypes import MCAP
from app.ros.msgtypes import typestore
from fuzzyocc import FuzzyMap

ROOM_HALF_M = 10.0
T0_NS = 1_700_000_000 * 10**9


def _ranges(x: float, y: float, yaw: float, beams: int, rng: np.random.Generator) -> np.ndarray:
    """Ranges to the walls of the room from (x, y), float32, with REP 117 specials sprinkled in."""
    angles = yaw - math.pi + np.arange(beams) * (2 * math.pi / beams)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (ROOM_HALF_M - x) / c, np.where(c < 0, (-ROOM_HALF_M - x) / c, np.inf))
        ty = np.where(s > 0, (ROOM_HALF_M - y) / s, np.where(s < 0, (-ROOM_HALF_M - y) / s, np.inf))
    ranges = np.minimum(tx, ty).astype(np.float32)
    ranges[rng.choice(beams, beams // 50, replace=False)] = np.nan
    ranges[rng.choice(beams, beams // 50, replace=False)] = np.inf
    return ranges


def write_bag(path: Path, scans: int, beams: int) -> Path:
    """The benchmark's bag (rosbag2, mcap); returns its .mcap file."""
    ts = typestore()
    t = ts.types
    rng = np.random.default_rng(0)

    def stamp(ns: int) -> object:
        return t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)

    def transform(parent: str, child: str, ns: int, x: float, y: float, yaw: float) -> object:
        return t["geometry_msgs/msg/TransformStamped"](
            header=t["std_msgs/msg/Header"](stamp=stamp(ns), frame_id=parent), child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))))

    def robot(seconds: float) -> tuple[float, float, float]:
        return 6.0 * math.cos(0.05 * seconds), 6.0 * math.sin(0.05 * seconds), 0.05 * seconds + math.pi / 2

    duration_s = scans / 10.0
    messages: list[tuple[str, str, int, object]] = [("/tf_static", "tf2_msgs/msg/TFMessage", T0_NS, t[
        "tf2_msgs/msg/TFMessage"](transforms=[transform("base_link", "laser", 0, 0.2, 0.0, 0.0)]))]
    for k in range(int(duration_s) + 2):
        ns = T0_NS + k * 10**9
        messages.append(("/tf", "tf2_msgs/msg/TFMessage", ns, t["tf2_msgs/msg/TFMessage"](
            transforms=[transform("map", "odom", ns, 0.0, 0.0, 0.0)])))
    for k in range(int(duration_s * 50) + 50):
        ns = T0_NS + k * 20_000_000
        x, y, yaw = robot(k / 50)
        messages.append(("/tf", "tf2_msgs/msg/TFMessage", ns, t["tf2_msgs/msg/TFMessage"](
            transforms=[transform("odom", "base_link", ns, x, y, yaw)])))
    for k in range(scans):
        ns = T0_NS + 10**8 + k * 100_000_000 + 7_000_000  # between TF samples
        x, y, yaw = robot((ns - T0_NS) / 1e9)
        ranges = _ranges(x + 0.2 * math.cos(yaw), y + 0.2 * math.sin(yaw), yaw, beams, rng)
        messages.append(("/scan", "sensor_msgs/msg/LaserScan", ns, t["sensor_msgs/msg/LaserScan"](
            header=t["std_msgs/msg/Header"](stamp=stamp(ns), frame_id="laser"), angle_min=-math.pi,
            angle_max=math.pi - 2 * math.pi / beams, angle_increment=2 * math.pi / beams, time_increment=0.0,
            scan_time=0.1, range_min=0.05, range_max=30.0, ranges=ranges, intensities=np.zeros(0, np.float32))))
    messages.sort(key=lambda m: m[2])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for topic, msgtype, ns, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(connections[topic], ns, ts.serialize_cdr(msg, msgtype))
    return next(path.glob("*.mcap"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=1000)
    parser.add_argument("--beams", type=int, default=720)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bag = write_bag(Path(tmp) / "drive", args.scans, args.beams)
        print(f"bag: {bag.stat().st_size / 2**20:.1f} MiB, {args.scans} LaserScans of {args.beams} beams, "
              f"TF at 50 Hz", flush=True)
        options = bags.BagOptions()
        read_s, fuse_s = [], []
        for _ in range(args.runs):
            started = time.perf_counter()
            read = bags.read_bag(bag, options, dims=2, limits=bags.DEFAULT_LIMITS)
            read_s.append(time.perf_counter() - started)
            scans = [s.scan for s in read.scans]
            spec = bags.grid_for(scans, 2, 0.05, 1.0, 16_000_000)
            FuzzyMap(spec).integrate_batch(scans[:2])  # numba's compilation, once, outside the clock
            occupancy = FuzzyMap(spec)
            started = time.perf_counter()
            for i in range(0, len(scans), 32):
                occupancy.integrate_batch(scans[i:i + 32])
            fuse_s.append(time.perf_counter() - started)
        assert len(read.scans) == args.scans, read.skipped
        best_read, best_fuse = min(read_s), min(fuse_s)
        print(f"in-process, {spec.shape[0]} x {spec.shape[1]} cells of 0.05 m (best of {args.runs}):")
        print(f"  read + place + convert: {best_read:.2f} s = {args.scans / best_read:,.0f} scans/s")
        print(f"  fusion:                 {best_fuse:.2f} s = {args.scans / best_fuse:,.0f} scans/s")
        print(f"  bag import:             {best_read + best_fuse:.2f} s = "
              f"{args.scans / (best_read + best_fuse):,.0f} scans/s", flush=True)

        upload_s = []
        settings = Settings(data_dir=Path(tmp) / "data", plan_warmup=False, plan_workers=1,
                            max_body_bytes=max(64 * 2**20, bag.stat().st_size + 1))
        with TestClient(create_app(settings)) as client:
            while client.get("/ready").json()["status"] == "starting":
                time.sleep(0.05)
            body = bag.read_bytes()
            for run in range(args.runs):
                name = f"drive{run}"
                client.post("/maps", json={"name": name, "resolution": 0.05, "origin": list(spec.origin),
                                           "size": list(spec.size)})
                started = time.perf_counter()
                response = client.post(f"/maps/{name}/bags", content=body,
                                       headers={"Content-Type": MCAP})
                upload_s.append(time.perf_counter() - started)
                assert response.status_code == 200 and response.json()["scans_fused"] == args.scans, response.text
        best = min(upload_s)
        print(f"upload (POST /maps/{{name}}/bags, in-process service, durable batches of 256): {best:.2f} s = "
              f"{args.scans / best:,.0f} scans/s")


if __name__ == "__main__":
    main()
