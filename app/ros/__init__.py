"""ROS 2 without ROS: message types (rosbags' typestore), LaserScan and PointCloud2 in, nav_msgs Path and
OccupancyGrid out (JSON, CDR, MCAP), and bags read as placed scans (with the size a bag will take)."""

__all__ = ["bags", "bagsize", "messages_in", "messages_out", "msgtypes"]
