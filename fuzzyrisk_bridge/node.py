"""The rclpy side of the bridge: subscribe to a LaserScan topic, look each scan's pose up in tf2,
hand both to :class:`fuzzyrisk_bridge.core.Bridge`. Nothing else happens here (the core is tested
without ROS); importing this module needs rclpy and tf2_ros (a sourced ROS 2 install).
"""

from __future__ import annotations

from typing import Any

import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.time import Time
from sensor_msgs.msg import LaserScan
from tf2_ros import Buffer, TransformListener

from fuzzyrisk_bridge.core import Bridge, BridgeConfig


class BridgeNode(Node):
    """``fuzzyrisk_bridge``: LaserScans on ``topic`` -> batches on ``POST /maps/{map}/scans``."""

    def __init__(self, config: BridgeConfig, *, topic: str, map_frame: str, tf_timeout_s: float) -> None:
        super().__init__("fuzzyrisk_bridge")
        self.map_frame = map_frame
        self.tf_timeout = Duration(seconds=tf_timeout_s)
        self.tf = Buffer()
        # its own thread, so that a lookup that waits for a transform does not stop TF from arriving
        self.tf_listener = TransformListener(self.tf, self, spin_thread=True)
        self.bridge = Bridge(config).start()
        self.create_subscription(LaserScan, topic, self.on_scan, qos_profile_sensor_data)
        self.get_logger().info(f"posting {topic} to {config.scans_url} (poses from tf2 in {map_frame!r})")

    def on_scan(self, msg: LaserScan) -> None:
        self.bridge.on_scan(msg, self.lookup)  # never raises

    def lookup(self, frame_id: str, stamp: Any) -> Any:
        """``T_map_laser`` at the scan's stamp (waits up to ``tf_timeout`` for TF to catch up)."""
        return self.tf.lookup_transform(self.map_frame, frame_id, Time.from_msg(stamp), timeout=self.tf_timeout)


def run(config: BridgeConfig, *, topic: str, map_frame: str, tf_timeout_s: float, ros_args: list[str]) -> None:
    """Spin the node until Ctrl-C or shutdown, then send what is queued (up to 5 s) and stop."""
    rclpy.init(args=ros_args)
    node = BridgeNode(config, topic=topic, map_frame=map_frame, tf_timeout_s=tf_timeout_s)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.bridge.close()
        node.get_logger().info(f"stopped: {node.bridge.stats.as_dict()}")
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
