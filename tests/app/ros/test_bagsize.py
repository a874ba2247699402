"""An uploaded bag is bounded by what its chunks decompress to, read from its headers before any chunk is
(``app/ros/bagsize.py``): a small compressed body cannot make the service decompress gigabytes."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_typestore

from app.ros import bagsize
from tests.app._ros import laser_msg
from tests.conftest import error_message

LASER = "sensor_msgs/msg/LaserScan"
BEAMS = 400_000  # 1.6 MB of float32 zeros: a few kB once compressed
MAP_2D = {"name": "bag", "dimensions": 2, "resolution": 0.1, "origin": [-5.0, -5.0], "size": [10.0, 10.0]}


def _ros1_zeros(path: Path) -> Path:
    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = path / "zeros.bag"
    writer = Writer1(bag)
    writer.set_compression(Writer1.CompressionFormat.BZ2)
    with writer:
        connection = writer.add_connection("/scan", LASER, typestore=ts)
        writer.write(connection, 10**9, ts.serialize_ros1(laser_msg(ts, np.zeros(BEAMS)), LASER))
    return bag


def _mcap_zeros(path: Path) -> Path:
    ts = get_typestore(Stores.ROS2_JAZZY)
    definition, _ = ts.generate_msgdef(LASER, ros_version=2)
    out = path / "zeros.mcap"
    with out.open("wb") as stream:
        writer = McapWriter(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(LASER, "ros2msg", definition.encode())
        channel = writer.register_channel("/scan", "cdr", schema)
        writer.add_message(channel, log_time=10**9, publish_time=10**9,
                           data=ts.serialize_cdr(laser_msg(ts, np.zeros(BEAMS)), LASER))
        writer.finish()
    return out


@pytest.mark.parametrize(("write", "content_type"), [(_ros1_zeros, "application/x-rosbag"),
                                                     (_mcap_zeros, "application/x-mcap")])
def test_a_bag_that_decompresses_beyond_the_limit_is_refused_before_it_is_read(
        make_client: Callable[..., TestClient], tmp_path: Path, write: Callable[[Path], Path],
        content_type: str) -> None:
    bag = write(tmp_path)
    declared = bagsize.decompressed_bytes(bag)
    assert declared >= 4 * BEAMS and bag.stat().st_size < declared / 20  # it is compressed
    small = make_client(max_bag_bytes=declared - 1)
    assert small.post("/maps", json=MAP_2D).status_code == 201
    refused = small.post("/maps/bag/bags", content=bag.read_bytes(), headers={"Content-Type": content_type})
    assert refused.status_code == 413 and "FUZZYRISK_MAX_BAG_BYTES" in error_message(refused)
    assert small.get("/maps/bag").json()["version"] == 0
    # the same bag within the limit is read (its beams, all zeros, are below range_min: skipped, said why)
    large = make_client(max_bag_bytes=declared, data_dir=tmp_path / "large")
    assert large.post("/maps", json=MAP_2D).status_code == 201
    taken = large.post("/maps/bag/bags", content=bag.read_bytes(), headers={"Content-Type": content_type})
    assert taken.status_code == 200, taken.text
    assert taken.json()["messages"] == 1 and taken.json()["scans_fused"] == 0


def test_the_declared_size_of_an_mcap_is_the_sum_of_its_chunks(tmp_path: Path) -> None:
    bag = _mcap_zeros(tmp_path)
    with bag.open("rb") as stream:
        chunks = [r for r in StreamReader(stream, emit_chunks=True).records if isinstance(r, Chunk)]
    assert chunks and bagsize.decompressed_bytes(bag) == sum(c.uncompressed_size for c in chunks)


@pytest.mark.parametrize("body", [b"", b"#ROSBAG V2.0\n\x40\x00\x00\x00op=", b"\x89MCAP0\r\n\x01\xff\xff"])
def test_a_damaged_header_is_not_a_size(tmp_path: Path, body: bytes) -> None:
    path = tmp_path / "damaged"
    path.write_bytes(body)
    with pytest.raises(bagsize.BagSizeUnknown):
        bagsize.decompressed_bytes(path)
