"""What a bag file will take once its chunks are decompressed, read from its own record headers.

A compressed chunk of zeros shrinks about a thousand times, so a body within the upload limit can
decompress to far more memory than the service has. Both containers declare each chunk's
uncompressed size in its record header (ROS 1: the chunk's ``size`` field; MCAP: the Chunk
record's ``uncompressed_size``), so the sum is known before a chunk is decompressed. rosbags
trusts those sizes when it decompresses; a chunk that lies about its size fails there instead.
"""

from __future__ import annotations

import struct
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
_ROS1_CHUNK = 0x05


class BagSizeUnknown(ValueError):
    """The record headers cannot be walked: not a bag, or a damaged one."""


def decompressed_bytes(path: Path) -> int:
    """Bytes the bag's chunks and loose messages take once decompressed, as its headers declare."""
    with path.open("rb") as stream:
        head = stream.read(len(ROS1_MAGIC))
    if head.startswith(ROS1_MAGIC):
        return _ros1(path)
    if head.startswith(MCAP_MAGIC):
        return _mcap(path)
    raise BagSizeUnknown("neither a ROS 1 .bag nor an .mcap file")


def _ros1_fields(header: bytes) -> dict[str, bytes]:
    fields, at = {}, 0
    while at + 4 <= len(header):
        (length,) = struct.unpack_from("<I", header, at)
        name, sep, value = header[at + 4:at + 4 + length].partition(b"=")
        if not sep or at + 4 + length > len(header):
            raise BagSizeUnknown("a ROS 1 record header field is malformed")
        fields[name.decode("latin-1")] = value
        at += 4 + length
    return fields


def _ros1(path: Path) -> int:
    """Every record in turn: a chunk counts its declared ``size``, any other record its data."""
    total = 0
    with path.open("rb") as stream:
        stream.seek(len(ROS1_MAGIC))
        while True:
            word = stream.read(4)
            if not word:
                return total
            (header_len,) = struct.unpack("<I", word.ljust(4, b"\0"))
            header = stream.read(header_len)
            data_word = stream.read(4)
            if len(header) < header_len or len(data_word) < 4:
                raise BagSizeUnknown("a ROS 1 record is cut short")
            (data_len,) = struct.unpack("<I", data_word)
            fields = _ros1_fields(header)
            op = fields.get("op", b"\xff")[:1]
            if op and op[0] == _ROS1_CHUNK:
                size = fields.get("size", b"")
                if len(size) != 4:
                    raise BagSizeUnknown("a ROS 1 chunk has no size")
                total += struct.unpack("<I", size)[0]
            else:
                total += data_len
            stream.seek(data_len, 1)


def _mcap(path: Path) -> int:
    """Chunks count their ``uncompressed_size``, messages outside chunks their data."""
    total = 0
    with path.open("rb") as stream:
        try:
            for record in StreamReader(stream, emit_chunks=True).records:
                if isinstance(record, Chunk):
                    total += record.uncompressed_size
                elif isinstance(record, Message):
                    total += len(record.data)
        except (McapError, EOFError, struct.error, ValueError) as exc:
            raise BagSizeUnknown(f"an MCAP record is malformed ({type(exc).__name__})") from None
    return total
