"""HTTP service: named fuzzy occupancy maps, scan fusion and risk-aware plans.

The folders, top to bottom (a folder imports only those below it; ``pyproject.toml``'s import-linter
contracts hold this):

- ``api``: the HTTP front (the app factory, routes, middleware, error handlers, the operator page);
  ``cli``: the command-line tools (``python -m app.import_log``, ``app.import_bag``, ``app.backup``).
- ``service``: ``MapService``, which wires the maps, their reads and their plans, and bag uploads.
- ``plans``: plan requests, the planner worker pool and what runs in a worker.
- ``reads``: a map's grid at one version and every answer made of it; recordings; the Foxglove view.
- ``maps``: the maps held in memory, the write path (a scan made durable, then fused), replay.
- ``ros``: ROS 2 message types, messages in and out, bags.
- ``scans``: a checked scan, and request bodies to scans.
- ``storage``: where maps are durable (SQLite, PostgreSQL), group commit, backup.
- ``ops``: the process's set-up, thread pools, warm-up, logs and metrics.
- ``schemas`` and ``formats``: the HTTP contract's bodies, and file formats, media types and ETags.
- ``errors`` and ``config``: the service's errors, and every ``FUZZYRISK_*`` setting.

``fuzzyocc`` (the maps) and ``planning`` (the planners) lie below all of it and know nothing of HTTP.
"""
