"""Configuration in one place: every knob is a ``FUZZYRISK_*`` environment variable.

``Settings`` validates itself and refuses unsafe values; ``create_app(settings)`` takes one
explicitly (tests build their own with a ``tmp_path`` data directory), and ``get_settings()``
reads the environment once for ``python -m app``.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

#: Shortest API key accepted: a guessable key is worse than none because it looks like protection.
MIN_API_KEY_LENGTH = 16


class Settings(BaseSettings):
    """Service configuration (environment variables ``FUZZYRISK_<FIELD>``, case-insensitive)."""

    model_config = SettingsConfigDict(env_prefix="FUZZYRISK_", extra="ignore")

    host: str = Field("127.0.0.1", description="Interface to listen on (0.0.0.0 in a container).")
    port: int = Field(8000, ge=1, le=65535, description="TCP port.")
    data_dir: Path = Field(
        Path("data"),
        description="Directory of the map database (created if missing); with FUZZYRISK_DATABASE_URL, of the "
        "replica's own files only (numba cache, plan grids, uploads on their way).",
    )
    database_url: SecretStr | None = Field(
        None,
        description="postgresql://user[:password]@host:port/dbname: keep the maps in PostgreSQL, where any number of "
        "replicas of the service share them (a fleet); unset or empty = SQLite in the data directory.",
    )
    map_idle_s: float = Field(
        600.0, gt=0, le=86_400,
        description="With FUZZYRISK_DATABASE_URL: a map no request used for this long is dropped from the replica's "
        "memory (loaded again from the database at its next request).",
    )
    api_key: SecretStr | None = Field(
        None,
        description="Bearer token every API call must carry; unset or empty = no authentication.",
    )
    max_body_bytes: int = Field(
        64 * 2**20, ge=1024,
        description="Largest upload body (scans, bags, a saved map imported), bytes (413 beyond); also the most a "
        "saved map's zipped image may inflate to.",
    )
    max_json_body_bytes: int = Field(
        8 * 2**20, ge=1024,
        description="Largest body of every other route (maps, risk queries, plans), bytes (413 beyond): "
        "100,000 query points as JSON take about 4 MB.",
    )
    max_bag_bytes: int = Field(
        512 * 2**20, ge=1024,
        description="Most bytes an uploaded bag's chunks may take decompressed, as its record headers declare "
        "(413 beyond, before any chunk is read).",
    )
    max_scans_per_batch: int = Field(256, ge=1, description="Most scans in one POST /maps/{name}/scans.")
    max_batch_cells: int = Field(
        400_000_000, ge=1,
        description="Most cells one batch's rays may walk, estimated before it is stored (413 beyond): about "
        "40 s of one fusion thread at 10 M cells a second.",
    )
    max_rays_per_scan: int = Field(
        2_000_000, ge=1, description="Most ranges in a LaserScan, or points in a point cloud."
    )
    max_map_cells: int = Field(
        16_000_000, ge=1,
        description="Most cells one map holds in memory (507 beyond): a fuzzy map holds a cell of each mixed block, "
        "one for each uniform block and none for space no scan reached (at most about 13 bytes a cell for the default "
        "engine); a bayes map its whole box. A batch is refused once the map holds this many (clear a region, set "
        "forget_beyond or delete the map); a batch under it may pass it by at most FUZZYRISK_MAX_NEW_CELLS_PER_BATCH.",
    )
    max_new_cells_per_batch: int = Field(
        16_000_000, ge=1,
        description="Most cells one batch may make a fuzzy map hold anew (413 beyond, before it is stored): the "
        "cells of every block its beams reach, counted as if the map held none of them yet.",
    )
    max_bodies_in_flight_bytes: int = Field(
        256 * 2**20, ge=1024,
        description="Most bytes of request bodies received and not yet answered, all requests together (503 beyond).",
    )
    body_read_timeout_s: float = Field(
        30.0, gt=0.0, le=3600.0, description="Longest wait for the next chunk of a request body, seconds (408 beyond)."
    )
    body_timeout_s: float = Field(
        120.0, gt=0.0, le=86400.0,
        description="Longest time a whole request body may take to arrive, seconds (408 beyond): a body trickled "
        "a byte at a time passes the per-chunk timeout; 64 MiB in 120 s is 0.5 MiB/s.",
    )
    header_timeout_s: float = Field(
        10.0, gt=0.0, le=3600.0,
        description="Longest time a request's headers may take to arrive, from the connection or the previous "
        "response, seconds (the connection is closed beyond).",
    )
    max_maps: int = Field(100, ge=1, description="Most maps the service holds (507 beyond).")
    max_total_cells: int = Field(
        400_000_000, ge=1,
        description="Most cells of all maps together (507 beyond): about 13 bytes a cell at worst for the default "
        "engine, so the default bounds the maps' memory near 5 GB.",
    )
    max_query_points: int = Field(100_000, ge=1, description="Most points in one risk query.")
    max_path_points: int = Field(
        10_000, ge=1,
        description="Most points in one path check (413 beyond): a plan's path has a point a cell, so 10,000 points "
        "are 500 m at 0.05 m.",
    )
    max_trajectory_poses: int = Field(
        1_000_000, ge=1,
        description="Most poses in a map's trajectory (GET /maps/{name}/trajectory: one per stored scan; 413 "
        "beyond): about 200 bytes of JSON each; and in a corrected one (PUT /maps/{name}/trajectory).",
    )
    rebuild_lease_s: float = Field(
        10.0, ge=0.5, le=3600.0,
        description="Seconds a replica holds a map's rebuild at a corrected trajectory without reporting progress "
        "(it reports every second): after a kill -9, the restarted service (or, on a fleet, another replica) resumes "
        "the rebuild once this has run out.",
    )
    max_plan_time_s: float = Field(30.0, gt=0.0, le=3600.0, description="Largest plan time_limit, seconds.")
    plan_workers: int = Field(2, ge=1, le=64, description="Planner worker processes.")
    plan_workers_per_map: int | None = Field(
        None, ge=1, le=64,
        description="Planner workers one map's plans may hold at once; unset: all but one (at least one), so "
        "that a map flooded with plans leaves a worker to the others and a core to scans and reads.",
    )
    plan_queue: int = Field(8, ge=1, description="Plans waiting for a worker before 503 answers (one map: half).")
    plan_warmup: bool = Field(True, description="Start the planner processes at startup, not at the first plan.")
    native_planning: bool = Field(
        True,
        description="Run the planners' validity, motion and cost callbacks as compiled code inside OMPL "
        "(checked at first use, Python fallback with a warning); false: always the Python callbacks.",
    )
    plan_cache_bytes: int = Field(
        256 * 2**20, ge=0,
        description="Bytes of map grids kept for the planner workers: the files of the map versions planned on "
        "(<data dir>/plan-grids), and, in each worker, the fields built from them with their dilations; 0: "
        "every plan ships its grid to a worker, which keeps nothing.",
    )
    max_pending_batches: int = Field(
        32, ge=1,
        description="Scan batches one map may hold in line (bodies arriving, parsed, committing or fusing) before 503.",
    )
    fusion_threads: int = Field(2, ge=1, le=64, description="Threads that fuse scans (different maps in parallel).")
    split_threads: int = Field(
        0, ge=0, le=64,
        description="Threads one batch's fusion is split between (its rays, then its cells), at the priority of the "
        "thread fusing it; 0: one per CPU. The map is the same, bit for bit, for any value.",
    )
    read_threads: int = Field(
        2, ge=1, le=64,
        description="Threads that read and encode grids (risk, exports, queries): apart from fusion's, so that a "
        "read of one map never waits behind the fusion of others.",
    )
    heavy_read_share: float = Field(
        0.25, gt=0.0, le=1.0,
        description="Share of the time that reads of big maps (more than 4 M cells) take together, from their "
        "copy to their last byte sent: they take turns, one at a time, and after each the next waits "
        "(1 / share - 1) times as long as it took.",
    )
    heavy_read_queue: int = Field(8, ge=1, description="Reads of big maps waiting for their turn before 503.")
    snapshot_every: int = Field(200, ge=1, description="Snapshot a map after this many batches since the last.")
    disk_reserve_bytes: int = Field(
        16 * 2**20, ge=0,
        description="A file of this many bytes kept in the data directory and given up when a map deletion meets "
        "a full disk, so that space can still be freed through the API (0: none).",
    )
    snapshot_log_bytes: int = Field(
        256 * 2**20, ge=1,
        description="Snapshot a map once its batches since the last snapshot take this many bytes: a map's disk is "
        "its snapshot plus at most this much log (and one batch).",
    )
    max_history_bytes: int = Field(
        2**30, ge=0,
        description="Most bytes of a map's history (its stored batches, which a rebuild re-fuses): beyond, the oldest "
        "are folded into the base snapshot a rebuild starts from, down to about 3/4 of this; never those after the "
        "restart snapshot (FUZZYRISK_SNAPSHOT_LOG_BYTES bounds them). 0: no history beyond what a restart needs.",
    )
    snapshot_log_cells: int = Field(
        2_000_000_000, ge=1,
        description="Snapshot a map once its batches since the last snapshot walk this many cells in all (their cast "
        "work, as FUZZYRISK_MAX_BATCH_CELLS counts it): a restart replays at most that much fusion for the map "
        "(and one batch), about 10 s on 2 cores.",
    )
    max_recording_bytes: int = Field(
        256 * 2**20, ge=1024,
        description="Most bytes of messages in one MCAP export of a map (GET /maps/{name}/export/mcap: its grid and "
        "the scans of its batch log), counted before the file is built (413 beyond); the file is built in memory.",
    )
    graceful_timeout_s: float = Field(
        30.0, gt=0.0, description="On SIGTERM, wait this long for requests in flight before stopping."
    )
    log_format: Literal["json", "kv"] = Field("json", description="json (one object a line) or kv (key=value).")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field("INFO", description="Logging threshold.")
    foxglove_port: int | None = Field(
        None, ge=1, le=65535,
        description="Serve the live view to Foxglove (WebSocket) on this port; unset: off. Needs the foxglove extra.",
    )
    foxglove_host: str = Field(
        "127.0.0.1", description="Interface of the Foxglove live view: it has no authentication, so loopback by default."
    )
    foxglove_interval_s: float = Field(
        1.0, ge=0.05, le=3600.0,
        description="Shortest time between two publications of one map's grid to Foxglove, seconds.",
    )
    foxglove_max_cells: int = Field(
        1_000_000, ge=10_000, le=4_000_000,
        description="Most cells of a grid published to Foxglove (8 bytes each): a larger map is shown in k x k "
        "blocks, each its cells' largest risk.",
    )

    @field_validator("api_key", "foxglove_port", "database_url", "plan_workers_per_map", mode="before")
    @classmethod
    def _empty_key_is_none(cls, value: object) -> object:
        # FUZZYRISK_API_KEY= (empty) in a compose file means "no key", not "the empty key" (and
        # FUZZYRISK_FOXGLOVE_PORT= means off)
        if value is None or (isinstance(value, str) and value == ""):
            return None
        return value

    @field_validator("api_key")
    @classmethod
    def _key_long_enough(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None and len(value.get_secret_value()) < MIN_API_KEY_LENGTH:
            raise ValueError(
                f"FUZZYRISK_API_KEY must have at least {MIN_API_KEY_LENGTH} characters "
                "(e.g. python -c 'import secrets; print(secrets.token_urlsafe(32))')"
            )
        return value

    @property
    def shared_storage(self) -> bool:
        """Maps in a database other replicas may write too (PostgreSQL): each map is loaded when first asked for and
        caught up with the database before every read (``app.replica``)."""
        return self.database_url is not None

    @property
    def database_path(self) -> Path:
        """The SQLite file holding every map."""
        return self.data_dir / "fuzzyrisk.sqlite3"

    @property
    def temp_dir(self) -> Path:
        """``<data dir>/tmp``: an uploaded bag's file while it is read (on the data directory's disk, not in a
        tmpfs /tmp that is memory), and the process's temporary files when the system has no writable one."""
        return self.data_dir / "tmp"

    @property
    def numba_cache_dir(self) -> Path:
        """Where compiled kernels are cached: numba's own ``NUMBA_CACHE_DIR`` when set, else ``<data dir>/numba-cache``.

        In the data directory because that is writable wherever the service runs (a read-only root, an
        installed package owned by another user) and belongs to the machine that compiled the kernels
        (numba keys them to the CPU): compiled once where they run, loaded at every later start.
        """
        return Path(os.environ.get("NUMBA_CACHE_DIR") or self.data_dir / "numba-cache")


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """Settings from the environment, read once."""
    return Settings()
