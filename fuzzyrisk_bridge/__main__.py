"""``python -m fuzzyrisk_bridge`` (installed as ``fuzzyrisk-bridge``): run the ROS 2 bridge node.

Options not listed below (``--ros-args ...``) go to rclpy. The API key comes from
``--api-key`` or ``FUZZYRISK_API_KEY``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from importlib import metadata

from fuzzyrisk_bridge.core import BridgeConfig

#: Exit status when the node cannot start (no rclpy, a bad option).
EXIT_STARTUP_FAILURE = 1


def _version() -> str:
    """The installed fuzzyrisk's version; the bridge may run from a checkout on PYTHONPATH, never installed."""
    try:
        return metadata.version("fuzzyrisk")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fuzzyrisk_bridge",
                                     description="post a ROS 2 LaserScan topic to a fuzzyrisk map")
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the fuzzyrisk service (default %(default)s)")
    parser.add_argument("--map", required=True, dest="map_name", help="the map to fuse into (it must exist)")
    parser.add_argument("--api-key", default=os.environ.get("FUZZYRISK_API_KEY"),
                        help="bearer key (default: $FUZZYRISK_API_KEY)")
    parser.add_argument("--topic", default="scan", help="sensor_msgs/LaserScan topic (default %(default)s)")
    parser.add_argument("--map-frame", default="map", help="tf2 frame of the map (default %(default)s)")
    parser.add_argument("--tf-timeout", type=float, default=0.1, help="seconds to wait for a scan's transform")
    parser.add_argument("--batch-size", type=int, default=10, help="scans per POST (default %(default)s)")
    parser.add_argument("--max-delay", type=float, default=0.5, help="longest a scan waits for its batch, s")
    parser.add_argument("--queue-size", type=int, default=200, help="scans held while the service is slow")
    parser.add_argument("--timeout", type=float, default=5.0, help="per request, s (default %(default)s)")
    parser.add_argument("--version", action="version", version=f"%(prog)s (fuzzyrisk) {_version()}")
    args, ros_args = parser.parse_known_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        config = BridgeConfig(url=args.url, map_name=args.map_name, api_key=args.api_key, batch_size=args.batch_size,
                              max_delay_s=args.max_delay, queue_size=args.queue_size, timeout_s=args.timeout)
    except ValueError as exc:
        print(f"fuzzyrisk-bridge: {exc}", file=sys.stderr)
        return EXIT_STARTUP_FAILURE
    try:
        from fuzzyrisk_bridge import node
    except ImportError as exc:
        print(f"fuzzyrisk-bridge: ROS 2 is not importable ({exc}): source your ROS 2 install first, e.g. "
              "'source /opt/ros/jazzy/setup.bash', in a Python that sees this package", file=sys.stderr)
        return EXIT_STARTUP_FAILURE
    node.run(config, topic=args.topic, map_frame=args.map_frame, tf_timeout_s=args.tf_timeout,
             ros_args=[sys.argv[0], *ros_args])
    return 0


if __name__ == "__main__":
    sys.exit(main())
