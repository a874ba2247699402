"""What a lidar's cloud costs before its fusion: its PointCloud2 read from the CDR body, then its admission.

    python3 dev.py bench cloudparse [--repeat N] [--data DIR]

The cloud is what ``ouster_ros`` publishes for an OS-1-128 at 1024 x 10 Hz: 128 rows of 1,024 points,
``point_step`` 48 (x y z float32 first, then intensity, t, reflectivity, ring, ambient, range), a
tenth of them no-returns (NaN), as ``POST /maps/{name}/scans`` receives it
(``application/vnd.ros2.sensor_msgs.msg.PointCloud2+cdr``). Rows: that cloud; dense; with 16 bytes
of padding at each row's end; and big-endian (the general path, field by field).

For each: the CPU time (median of ``--repeat``) of ``app.maps.ingest.parse`` (the body to a checked
``PointCloud``, fuzzyocc's placing of the points included) and of its first half (the body to the
sensor-frame points, ``messages_in.sensor_scan``), and the most memory either allocated at once
(tracemalloc). docs/DESIGN.md section 8.4 quotes them.

Then the admission of the three real Ouster frames (``ouster/`` of the data directory, ``range_max`` 30 m, every
height) into a growing map at 0.1 and 0.2 m: the CPU time (median of ``--repeat``, a frame a call) of
``fuzzyocc.allocation_bound`` (the cells of every block the rays cross: ``raycast.cross_into``'s marks) against the
same bound counted by a cast over the lattice of blocks (``cast_into``, what it ran before), which must give the same
number, and of ``cast_work`` beside them.
"""

from __future__ import annotations

import argparse
import statistics
import time
import tracemalloc
from collections.abc import Callable
from typing import Any

import numpy as np

from app.maps import ingest
from bench import _data, bench_extent
from fuzzyocc import LatticeSpec, PointCloud, allocation_bound, cast_work
from fuzzyocc.blockgrid import BLOCK_SHIFT_3D
from fuzzyocc._block_table import BlockIndex
from fuzzyocc.raycast import Lattice, cast_into
from fuzzyocc.maps import scan_parts
from app.ros import messages_in
from app.ros.msgtypes import typestore
from app.scans import Limits

HEIGHT, WIDTH = 128, 1024
#: ouster_ros's point: name -> (numpy type, offset); 48 bytes.
OUSTER_POINT = {"x": ("f4", 0), "y": ("f4", 4), "z": ("f4", 8), "intensity": ("f4", 16), "t": ("u4", 20),
                "reflectivity": ("u2", 24), "ring": ("u2", 26), "ambient": ("u2", 28), "range": ("u4", 32)}
POINT_STEP = 48
_DATATYPES = {"f4": 7, "u4": 6, "u2": 4}
QUERY = {"x": "0.5", "y": "-0.25", "z": "1.2", "qx": "0.0", "qy": "0.0", "qz": "0.2588190451",
         "qw": "0.9659258263", "range_max": "20.0"}
LIMITS = Limits(max_scans=256, max_rays=2_000_000)


def os1_cloud(*, no_returns: float = 0.1, row_pad: int = 0, bigendian: bool = False, seed: int = 1) -> bytes:
    """The CDR bytes of an OS-1-128 cloud of walls 1-8 m away, ``no_returns`` of its points NaN."""
    rng = np.random.default_rng(seed)
    order = ">" if bigendian else "<"
    layout = np.dtype({"names": list(OUSTER_POINT), "formats": [order + t for t, _ in OUSTER_POINT.values()],
                       "offsets": [o for _, o in OUSTER_POINT.values()], "itemsize": POINT_STEP})
    azimuth = np.linspace(0.0, 2.0 * np.pi, WIDTH, endpoint=False)[None, :]
    elevation = np.linspace(-0.39, 0.39, HEIGHT)[:, None]
    r = rng.uniform(1.0, 8.0, (HEIGHT, WIDTH))
    points = np.zeros((HEIGHT, WIDTH), dtype=layout)
    points["x"] = r * np.cos(elevation) * np.cos(azimuth)
    points["y"] = r * np.cos(elevation) * np.sin(azimuth)
    points["z"] = r * np.sin(elevation)
    missing = rng.random((HEIGHT, WIDTH)) < no_returns
    for axis in "xyz":
        points[axis][missing] = np.nan
    points["ring"] = np.arange(HEIGHT)[:, None]
    rows = points.view(np.uint8)  # (HEIGHT, WIDTH * POINT_STEP)
    data = np.concatenate([rows, np.zeros((HEIGHT, row_pad), dtype=np.uint8)], axis=1).ravel()
    ts = typestore()
    field = ts.types["sensor_msgs/msg/PointField"]
    fields = [field(name=name, offset=offset, datatype=_DATATYPES[t], count=1) for name, (t, offset) in OUSTER_POINT.items()]
    header = ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=0),
                                             frame_id="os_lidar")
    msg = ts.types[messages_in.POINT_CLOUD2](
        header=header, height=HEIGHT, width=WIDTH, fields=fields, is_bigendian=bigendian, point_step=POINT_STEP,
        row_step=WIDTH * POINT_STEP + row_pad, data=data, is_dense=not missing.any())
    return bytes(ts.serialize_cdr(msg, messages_in.POINT_CLOUD2))


def _cpu_ms(run: Callable[[], Any], repeat: int) -> float:
    run()  # once before: scipy's and rosbags' first calls build what later ones reuse
    times = []
    for _ in range(repeat):
        start = time.thread_time()
        run()
        times.append(time.thread_time() - start)
    return statistics.median(times) * 1e3


def _peak_mb(run: Callable[[], Any]) -> float:
    tracemalloc.start()
    try:
        run()
        return tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()


def _cast_bound(spec: LatticeSpec, cloud: PointCloud) -> int:
    """``allocation_bound`` of one cloud on a growing 3-D map as it was counted before: a cast over the lattice of
    blocks, its evidence, rows and combine made and thrown away."""
    side = 1 << BLOCK_SHIFT_3D
    lattice, index = Lattice((0.0,) * 3, spec.resolution * side, None), BlockIndex()
    for part in scan_parts(cloud):
        rays = cloud.to_rays(beams=part)
        n = rays.ranges.size
        cast_into(lattice, index, (0, 0, 0), np.repeat(rays.origin[None], n, axis=0), rays.directions, rays.ranges,
                  np.full(n, np.nan), np.ones(n), np.array([0, n]), unknown_from=np.inf, split=False)
    return index.n * side**3


def admission(repeat: int) -> None:
    """The Ouster frames' allocation bound against the cast's count of it, and their work estimate (module doc)."""
    clouds = bench_extent.ouster_clouds(_data.needed("ouster"))
    print(f"\n{'Ouster frames (107 k rays), a frame':36s} {'bound':>9s} {'by a cast':>10s} {'ratio':>7s} "
          f"{'cast_work':>10s} {'bound, cells':>13s}")
    for resolution in (0.1, 0.2):
        spec = LatticeSpec(ndim=3, resolution=resolution)
        bounds = [allocation_bound(spec, [cloud]) for cloud in clouds]
        if bounds != [_cast_bound(spec, cloud) for cloud in clouds]:
            raise SystemExit(f"the bound at {resolution} m differs from the cast's count: {bounds}")
        ours = statistics.median(_cpu_ms(lambda c=c: allocation_bound(spec, [c]), repeat) for c in clouds)
        peer = statistics.median(_cpu_ms(lambda c=c: _cast_bound(spec, c), repeat) for c in clouds)
        work = statistics.median(_cpu_ms(lambda c=c: cast_work(spec, [c]), repeat) for c in clouds)
        print(f"{f'at {resolution} m':36s} {ours:6.1f} ms {peer:7.1f} ms {peer / ours:6.2f}x {work:7.1f} ms "
              f"{statistics.median(bounds):13,.0f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=60, help="runs of each (the median is shown)")
    _data.add_option(parser)
    args = parser.parse_args()
    _data.use(args)
    media = messages_in.media_type(messages_in.POINT_CLOUD2)
    pose = messages_in.pose_from_query({k: float(v) for k, v in QUERY.items()})
    warm = os1_cloud()
    for _ in range(args.repeat):  # the first clouds of a process cost more (malloc's thresholds adapt): not measured
        ingest.parse(warm, media, QUERY, 3, LIMITS)
    print(f"{'OS-1-128 cloud, 131,072 points':36s} {'to points':>10s} {'peak':>8s} {'parse':>9s} {'peak':>8s} {'fused':>7s}")
    for label, kwargs in (("point_step 48, 10 % no-returns", {}), ("dense", {"no_returns": 0.0}),
                          ("rows padded 16 bytes", {"row_pad": 16}), ("big-endian (field by field)", {"bigendian": True})):
        body = os1_cloud(**kwargs)

        def to_points(body: bytes = body) -> Any:
            msg = messages_in.decode(body, messages_in.POINT_CLOUD2)
            return messages_in.sensor_scan(msg, messages_in.POINT_CLOUD2, pose, dims=3, limits=LIMITS, range_max=20.0)

        def parse(body: bytes = body) -> Any:
            return ingest.parse(body, media, QUERY, 3, LIMITS)

        fused = len(parse()[0].points)
        print(f"{label:36s} {_cpu_ms(to_points, args.repeat):7.2f} ms {_peak_mb(to_points):5.1f} MB "
              f"{_cpu_ms(parse, args.repeat):6.2f} ms {_peak_mb(parse):5.1f} MB {fused:7,d}")
    admission(max(3, args.repeat // 10))


if __name__ == "__main__":
    main()
