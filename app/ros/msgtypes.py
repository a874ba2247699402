"""The ROS 2 message types and ROS time, shared by messages in (``app.ros.messages_in``, ``app.cli.import_bag``) and out
(``app.ros.messages_out``).

Messages are data, as in rosbags: one typestore, built from ROS 2 Jazzy's message definitions (no ROS
install). LaserScan, PointCloud2, PointField, Header, OccupancyGrid and Path are the same in every ROS 2
release from Humble on (a test posts bodies of both). Stamps are ROS time without simulation time: Unix
time as ``builtin_interfaces/Time`` ``{"sec", "nanosec"}``.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

#: Message definitions of ROS 2 Jazzy.
STORE = Stores.ROS2_JAZZY
NS_PER_S = 1_000_000_000
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


@functools.cache
def typestore() -> Typestore:
    """The message types, built once (about 0.1 s): every CDR body is read and written with these."""
    return get_typestore(STORE)


def ros_time_of_ns(nanoseconds: int) -> dict[str, int]:
    """``builtin_interfaces/Time`` of Unix nanoseconds (``time.time_ns()``)."""
    sec, nanosec = divmod(int(nanoseconds), NS_PER_S)
    return {"sec": sec, "nanosec": nanosec}


def ns_of_ros_time(stamp: Mapping[str, int] | Any) -> int:
    """Unix nanoseconds of a ``builtin_interfaces/Time``: a message's stamp (``.sec``, ``.nanosec``) or its JSON dict."""
    if isinstance(stamp, Mapping):
        return int(stamp["sec"]) * NS_PER_S + int(stamp["nanosec"])
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ros_time_of(when: datetime) -> dict[str, int]:
    """``builtin_interfaces/Time`` of an aware datetime, exact to the microsecond (integer arithmetic)."""
    delta = when - _EPOCH
    micros = (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
    return ros_time_of_ns(micros * 1000)


def ros_time_of_iso(text: str) -> dict[str, int]:
    """``builtin_interfaces/Time`` of an ISO 8601 time with offset (the service's ``created``/``updated``)."""
    return ros_time_of(datetime.fromisoformat(text))
