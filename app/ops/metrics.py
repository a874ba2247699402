"""Prometheus metrics of one app instance (its own registry: several apps may live in one process)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

_LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class Metrics:
    """The service's counters and histograms, exposed at ``GET /metrics``."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.requests = Counter(
            "fuzzyrisk_http_requests", "HTTP requests answered", ["method", "route", "status"], registry=r
        )
        self.request_seconds = Histogram(
            "fuzzyrisk_http_request_duration_seconds", "Time to answer a request", ["method", "route"],
            buckets=_LATENCY_BUCKETS, registry=r,
        )
        self.scans_fused = Counter("fuzzyrisk_scans_fused", "Scans fused into maps", ["model"], registry=r)
        self.catch_ups = Counter(
            "fuzzyrisk_catch_ups", "Times a map was brought up to its stored version (batches of other replicas)",
            registry=r,
        )
        self.evictions = Counter(
            "fuzzyrisk_map_evictions", "Maps dropped from memory (idle, or deleted through another replica)",
            ["reason"], registry=r,
        )
        self.rays = Counter("fuzzyrisk_rays", "Beams (ranges or points) fused", ["model"], registry=r)
        self.cells_updated = Counter("fuzzyrisk_cells_updated", "Cell updates made by fusion", ["model"], registry=r)
        self.batches_rejected = Counter(
            "fuzzyrisk_batches_rejected", "Scan batches refused (4xx, or 503 for a full line)", ["reason"], registry=r
        )
        self.fusion_seconds = Histogram(
            "fuzzyrisk_fusion_duration_seconds", "Time to fuse one batch (excluding the disk commit)", ["model"],
            buckets=_LATENCY_BUCKETS, registry=r,
        )
        self.commit_seconds = Histogram(
            "fuzzyrisk_batch_commit_duration_seconds",
            "Time to make one batch durable: the wait for the writer thread, and its transaction (fsync)",
            buckets=_LATENCY_BUCKETS, registry=r,
        )
        self.commit_groups = Histogram(
            "fuzzyrisk_batch_commit_group_size", "Batches made durable by one transaction (group commit)",
            buckets=(1, 2, 3, 4, 6, 8, 12, 16, 32, 64), registry=r,
        )
        self.plan_seconds = Histogram(
            "fuzzyrisk_plan_duration_seconds", "Time to answer a plan, queueing included", ["planner", "outcome"],
            buckets=_LATENCY_BUCKETS, registry=r,
        )
        self.plan_grids = Counter(
            "fuzzyrisk_plan_grids",
            "Plans by how their map grid reached the worker: shared (already published for that map version), "
            "published (the first plans on a version: its grid was written for them), shipped (sent with the plan: "
            "publishing off, over FUZZYRISK_PLAN_CACHE_BYTES, or the data directory refused the file)",
            ["source"], registry=r,
        )
        self.plan_grid_bytes = Gauge(
            "fuzzyrisk_plan_grid_bytes", "Bytes of map grids published for the planner workers", registry=r
        )
        self.maps = Gauge("fuzzyrisk_maps", "Maps held", registry=r)
        self.batches_in_line = Gauge(
            "fuzzyrisk_batches_in_line", "Scan batches accepted or arriving and not yet applied, all maps",
            registry=r,
        )
        self.longest_fusion_job = Gauge(
            "fuzzyrisk_longest_fusion_job_seconds", "How long the oldest job in a fusion thread has run (0: idle)",
            registry=r,
        )
        self.snapshots = Counter("fuzzyrisk_snapshots", "Map snapshots written", registry=r)
        self.snapshot_failures = Counter(
            "fuzzyrisk_snapshot_failures", "Map snapshots that storage refused (retried later)", registry=r
        )
        self.history_folds = Counter(
            "fuzzyrisk_history_folds", "Oldest batches of a map's history folded into its base snapshot", registry=r
        )
        self.rebuilds = Counter(
            "fuzzyrisk_rebuilds", "Rebuilds of a map at a corrected trajectory, by how they ended (done, failed, "
            "superseded: a newer correction or the map's deletion stopped it)", ["result"], registry=r
        )
        self.history_fold_failures = Counter(
            "fuzzyrisk_history_fold_failures", "Folds of a map's history that failed (tried again after the next "
            "snapshot)", registry=r
        )
