"""Durable map storage: a small interface, an embedded SQLite implementation and a PostgreSQL one.

A map on disk is its metadata, its history (every batch committed after its base
snapshot, in order), its base snapshot (the map's arrays at the version the history
starts after; none while no batch has left the history) and its restart snapshot
(the map's arrays at a newer version). The service commits a batch before it
applies it and answers, so a batch that got a 200 survives ``kill -9``; a restart
loads the restart snapshot and replays the batches after it (fusion is
deterministic, so the risk is bit for bit the same). A snapshot drops nothing: the
oldest batches leave the history only when folded into a new base
(``write_base``), which a rebuild from the history starts from.

The store, not the service, gives each batch its version: several replicas of the
service may write one database (``app.storage.postgres``), and the map's row is what
orders their writes. A batch that could not be applied stays as a tombstone (an
empty payload), so a version once given out is never given again.

Payloads are opaque bytes here: storage knows nothing of scans or maps.

``app.storage.base`` holds the ``Storage`` protocol, its records and errors; ``app.storage.sqlite`` the
default store. Both are re-exported here. ``app.storage.postgres`` is not: it needs psycopg (the
``postgres`` extra), imported only when ``FUZZYRISK_DATABASE_URL`` is set.
"""

from app.storage.base import (
    INLINE_BYTES,
    TOMBSTONE,
    BatchRecord,
    CommitUncertain,
    MapGone,
    MapHead,
    NameTaken,
    Storage,
    StorageUnavailable,
    StoredMap,
    checksum,
    head_of,
    read_map,
)
from app.storage.corrections import StoredCorrection, Superseded, Switch
from app.storage.sqlite import SqliteStorage, payload_directory

__all__ = [
    "INLINE_BYTES",
    "TOMBSTONE",
    "BatchRecord",
    "CommitUncertain",
    "MapGone",
    "MapHead",
    "NameTaken",
    "SqliteStorage",
    "Storage",
    "StorageUnavailable",
    "StoredCorrection",
    "StoredMap",
    "Superseded",
    "Switch",
    "checksum",
    "head_of",
    "payload_directory",
    "read_map",
]
