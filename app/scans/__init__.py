"""Scans in: request bodies (JSON batches, binary ``.npy`` or raw float32 scans) to checked fuzzyocc scans.

``scan`` builds a checked ``LaserScan`` or ``PointCloud`` for a map (its dimension, ``Limits``, the
ray count: ``check_rays``), and every way a scan comes in ends there: ``bodies`` reads JSON and binary
bodies, ``app.ros.messages_in`` ROS messages. ``scanview`` is the last scan as the web page draws it.
Nothing here stores or fuses: the batch log's bytes are ``app.maps.logcodec``'s.
"""

from app.scans.bodies import BINARY_TYPES, from_binary, from_json
from app.scans.scan import Limits, Scan, check_rays, finite_rows, laser_scan, point_cloud
from app.scans.scanview import MAX_VIEW_BEAMS, ScanView, scan_view

__all__ = [
    "BINARY_TYPES",
    "MAX_VIEW_BEAMS",
    "Limits",
    "Scan",
    "ScanView",
    "check_rays",
    "finite_rows",
    "from_binary",
    "from_json",
    "laser_scan",
    "point_cloud",
    "scan_view",
]
