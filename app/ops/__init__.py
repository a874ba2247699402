"""What the service's processes need to run: process set-up (the port, directories, parent death,
priorities), the forkserver, thread pools, kernel warm-up, logs and metrics.

Nothing is imported here: ``forkserver_preload`` must be the first module a forkserver imports.
"""

__all__ = ["forkserver", "forkserver_preload", "logs", "metrics", "process_setup", "threads", "warmup"]
