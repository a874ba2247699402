"""fuzzyrisk_bridge: a ROS 2 node that posts a robot's LaserScans to a fuzzyrisk service.

``core`` (pure Python, standard library only) does the work and is what the tests drive;
``node`` is the thin rclpy subscriber, imported only where rclpy is (a sourced ROS 2 install).
Run it with ``python -m fuzzyrisk_bridge --url http://127.0.0.1:8000 --map lab``.
"""

from fuzzyrisk_bridge.core import Bridge, BridgeConfig, BridgeStats, scan_to_json

__all__ = ["Bridge", "BridgeConfig", "BridgeStats", "scan_to_json"]
