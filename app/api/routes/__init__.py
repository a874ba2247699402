"""The routes, one module per resource: maps, scans, risk (and its ROS exports), plans, recordings, bags,
system probes, the API docs and the operator page."""

__all__ = ["bags", "docs", "maps", "plans", "recordings", "risk", "scans", "system", "ui"]
