"""What the service's processes need to run: process set-up (the port, directories, parent death,
priorities), the forkserver, thread pools, kernel warm-up (and saying when a command compiles), logs,
metrics, and the package's version.

Nothing is imported here: ``forkserver_preload`` must be the first module a forkserver imports.
"""

__all__ = ["compile_notice", "forkserver", "forkserver_preload", "logs", "metrics", "process_setup", "threads", "version",
           "warmup"]
