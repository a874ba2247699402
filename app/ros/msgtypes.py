"""The ROS 2 message types and ROS time, shared by messages in (``app.ros.messages_in``, ``app.cli.import_bag``) and out
(``app.ros.messages_out``).

Messages are data, as in rosbags: one typestore, built from ROS 2 Jazzy's message definitions (no ROS
install). LaserScan, PointCloud2, PointField, Header, OccupancyGrid and Path are the same in every ROS 2
release from Humble on (a test posts bodies of both). Stamps are ROS time without simulation time: Unix
time as ``builtin_interfaces/Time`` ``{"sec", "nanosec"}``.
"""

from __future__ import annotations

import functools
from datetime import UTC, datetime

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

# ROS time <-> nanoseconds is vocabulary the bodies share (a scan's header.stamp): defined there, used from here too
from app.schemas.common import NS_PER_S, ns_of_ros_time, ros_time_of_ns

__all__ = ["NS_PER_S", "STORE", "ns_of_ros_time", "ros_time_of", "ros_time_of_iso", "ros_time_of_ns", "typestore"]

#: Message definitions of ROS 2 Jazzy.
STORE = Stores.ROS2_JAZZY
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


@functools.cache
def typestore() -> Typestore:
    """The message types, built once (about 0.1 s): every CDR body is read and written with these."""
    return get_typestore(STORE)


def ros_time_of(when: datetime) -> dict[str, int]:
    """``builtin_interfaces/Time`` of an aware datetime, exact to the microsecond (integer arithmetic)."""
    delta = when - _EPOCH
    micros = (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
    return ros_time_of_ns(micros * 1000)


def ros_time_of_iso(text: str) -> dict[str, int]:
    """``builtin_interfaces/Time`` of an ISO 8601 time with offset (the service's ``created``/``updated``)."""
    return ros_time_of(datetime.fromisoformat(text))
