"""Genuine ROS messages for the tests, built and serialized with rosbags' typestores (no ROS install)."""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

STORES = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}
LASER_CT = "application/vnd.ros2.sensor_msgs.msg.LaserScan+cdr"
CLOUD_CT = "application/vnd.ros2.sensor_msgs.msg.PointCloud2+cdr"
#: sensor_msgs/PointField datatypes by numpy type code.
DATATYPES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def store(name: str) -> Any:
    return get_typestore(STORES[name])


def header(ts: Any, frame_id: str, stamp_ns: int = 0) -> Any:
    time = ts.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    if "seq" in ts.types["std_msgs/msg/Header"].__dataclass_fields__:  # a ROS 1 store
        return ts.types["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame_id)
    return ts.types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)


def laser_msg(ts: Any, ranges: Any, *, angle_min: float = -1.2, angle_increment: float = 0.02,
              range_min: float = 0.1, range_max: float = 8.0, frame_id: str = "laser", stamp_ns: int = 0) -> Any:
    ranges32 = np.asarray(ranges, dtype=np.float32)
    return ts.types["sensor_msgs/msg/LaserScan"](
        header=header(ts, frame_id, stamp_ns), angle_min=angle_min,
        angle_max=angle_min + angle_increment * (ranges32.size - 1), angle_increment=angle_increment,
        time_increment=0.0, scan_time=0.1, range_min=range_min, range_max=range_max, ranges=ranges32,
        intensities=np.full(ranges32.size, 100.0, dtype=np.float32))


def wall_ranges(n: int = 121, *, angle_min: float = -1.2, angle_increment: float = 0.02, wall: float = 2.5,
                seed: int = 3) -> np.ndarray:
    """float32 ranges of a wall ``wall`` m ahead, with each REP 117 special value sprinkled in."""
    angles = angle_min + angle_increment * np.arange(n)
    ranges = (wall / np.cos(angles)).astype(np.float32)
    rng = np.random.default_rng(seed)
    picks = rng.choice(n, size=16, replace=False)
    ranges[picks[:4]] = np.inf  # no return: free space to range_max
    ranges[picks[4:8]] = np.nan  # invalid
    ranges[picks[8:10]] = -np.inf  # too close
    ranges[picks[10:12]] = 0.05  # below range_min
    ranges[picks[12:14]] = 8.0  # at range_max: a no-return too
    return ranges


def cloud_msg(ts: Any, points: np.ndarray, *, extra: tuple[str, ...] = ("intensity",), dtype: str = "f4",
              bigendian: bool = False, height: int = 1, row_pad: int = 0, frame_id: str = "lidar",
              stamp_ns: int = 0, dense: bool | None = None, offsets: tuple[int, int, int] | None = None,
              point_step: int | None = None) -> Any:
    """A PointCloud2 of ``points`` (N, 3) as x, y, z fields of ``dtype``, plus float32 ``extra`` fields after them.

    ``height`` > 1 makes an organised cloud of ``height`` rows; ``row_pad`` adds bytes at each row's end.
    ``offsets`` places x, y, z in the point (packed from 0 by default), ``point_step`` pads each point to that size.
    """
    order = ">" if bigendian else "<"
    names = ["x", "y", "z", *extra]
    formats = [order + dtype] * 3 + [order + "f4"] * len(extra)
    if offsets is None:
        layout = np.dtype({"names": names, "formats": formats})
    else:
        size = np.dtype(dtype).itemsize
        after = max(offsets) + size
        layout = np.dtype({"names": names, "formats": formats,
                           "offsets": [*offsets, *range(after, after + 4 * len(extra), 4)]})
    if point_step is not None:
        layout = np.dtype({"names": names, "formats": formats,
                           "offsets": [layout.fields[n][1] for n in names], "itemsize": point_step})
    n = points.shape[0]
    assert n % height == 0
    width = n // height
    records = np.zeros(n, dtype=layout)
    for i, axis in enumerate("xyz"):
        records[axis] = points[:, i]
    for name in extra:
        records[name] = np.arange(n) % 97
    rows = records.tobytes()
    row_bytes = width * layout.itemsize
    data = b"".join(rows[r * row_bytes:(r + 1) * row_bytes] + b"\xee" * row_pad for r in range(height))
    field = ts.types["sensor_msgs/msg/PointField"]
    fields = [field(name=name, offset=layout.fields[name][1], datatype=DATATYPES[layout.fields[name][0].str[1:]],
                    count=1) for name in names]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=header(ts, frame_id, stamp_ns), height=height, width=width, fields=fields, is_bigendian=bigendian,
        point_step=layout.itemsize, row_step=row_bytes + row_pad, data=np.frombuffer(data, dtype=np.uint8),
        is_dense=bool(np.isfinite(points).all()) if dense is None else dense)


def cdr(ts: Any, msg: Any, *, little_endian: bool = True) -> bytes:
    return bytes(ts.serialize_cdr(msg, msg.__msgtype__, little_endian=little_endian))


def grids(client: Any, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The map's risk and observed mask, as ``GET /maps/{name}/risk.npy`` serves them."""
    out = []
    for layer in ("risk", "observed"):
        response = client.get(f"/maps/{name}/risk.npy", params={"layer": layer})
        assert response.status_code == 200, response.text
        out.append(np.load(io.BytesIO(response.content), allow_pickle=False))
    return out[0], out[1]
