"""Big payloads as files beside the SQLite database: written before the commit, outside the commit line."""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from app.storage.backup import backup
from app.storage.committer import GroupCommitter
from app.ops.metrics import Metrics
from app.storage.payloadfiles import PayloadFiles, Prefetched
from app.storage import (
    INLINE_BYTES,
    BatchRecord,
    CommitUncertain,
    MapGone,
    SqliteStorage,
    StorageUnavailable,
    payload_directory,
)

BIG = INLINE_BYTES + 1


def _payload(size: int, seed: int) -> bytes:
    return (seed.to_bytes(4, "little") * (size // 4 + 1))[:size]


@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / "data" / "fuzzyrisk.sqlite3"


@pytest.fixture
def store(path: Path) -> Iterator[SqliteStorage]:
    storage = SqliteStorage(path)
    storage.create_map("m", {"name": "m"}, "t0")
    yield storage
    storage.close()


def _append(store: SqliteStorage, payload: bytes, name: str = "m") -> int:
    return store.append_batches([BatchRecord(name, None, payload, "t", 1)])[0]


def _files(path: Path) -> list[str]:
    directory = payload_directory(path)
    return sorted(p.name for p in directory.iterdir()) if directory.is_dir() else []


def _rows(path: Path, sql: str) -> list[tuple[object, ...]]:
    with sqlite3.connect(path) as db:
        return db.execute(sql).fetchall()


def test_a_big_batch_is_a_file_and_loads_bit_for_bit(store: SqliteStorage, path: Path) -> None:
    big, small = _payload(BIG, 1), _payload(INLINE_BYTES, 2)
    assert [_append(store, big), _append(store, small)] == [1, 2]
    assert store.load_map("m").batches == [(1, big), (2, small)]  # type: ignore[union-attr]
    (file,) = _files(path)
    assert _rows(path, "SELECT seq, length(payload), file FROM batches ORDER BY seq") == \
        [(1, 0, file), (2, INLINE_BYTES, None)]  # the big one's row holds its file's name, not its bytes


def test_files_go_with_the_rows_that_name_them(store: SqliteStorage, path: Path) -> None:
    for k in range(3):
        _append(store, _payload(BIG, k))
    store.discard_batch("m", 2)
    assert len(_files(path)) == 2
    store.write_snapshot("m", 2, _payload(BIG, 10))  # a file itself; the batches it covers stay (the history)
    assert len(_files(path)) == 3
    assert store.write_base("m", 2, None)  # batches 1 and 2 folded: the snapshot becomes the base, file and all
    (base_file,) = _rows(path, "SELECT file FROM bases")[0]
    (batch_file,) = _rows(path, "SELECT file FROM batches WHERE seq = 3")[0]
    assert _files(path) == sorted([base_file, batch_file])
    store.write_snapshot("m", 3, _payload(BIG, 11))
    assert store.write_base("m", 3, _payload(BIG, 12))  # replaces the base's file; batch 3's goes with its row
    assert _files(path) == sorted(file for (file,) in _rows(path, "SELECT file FROM snapshots UNION ALL "
                                                                  "SELECT file FROM bases"))
    stored = store.load_map("m")
    assert stored is not None and (stored.snapshot_version, stored.snapshot) == (3, _payload(BIG, 11))
    store.write_snapshot("m", 2, _payload(BIG, 13))  # an older snapshot is no write: its file does not stay
    assert not store.write_base("m", 3, _payload(BIG, 14))  # nor a base as old as the stored one
    assert len(_files(path)) == 2
    store.delete_map("m")
    assert _files(path) == []


def test_a_base_snapshots_file_stays_when_the_store_opens_again(path: Path) -> None:
    # the sweep at open removes files no row names: a base's row names its file too
    first = SqliteStorage(path)
    first.create_map("m", {"name": "m"}, "t0")
    for k in range(3):
        _append(first, _payload(BIG, k))
    first.write_snapshot("m", 3, _payload(BIG, 10))
    assert first.write_base("m", 2, _payload(BIG, 12))
    first.close()
    reopened = SqliteStorage(path)
    try:
        history = reopened.load_history("m")
        assert history is not None and not history.damage
        assert (history.snapshot_version, history.snapshot) == (2, _payload(BIG, 12))
    finally:
        reopened.close()


def test_a_failed_commit_leaves_no_file(store: SqliteStorage, path: Path) -> None:
    with pytest.raises(MapGone):
        store.append_batches([BatchRecord("m", None, _payload(BIG, 1), "t", 1),
                              BatchRecord("gone", None, _payload(BIG, 2), "t", 1)])
    assert _files(path) == [] and store.load_map("m").batches == []  # type: ignore[union-attr]


def test_files_no_row_names_are_removed_at_the_next_open(path: Path) -> None:
    store = SqliteStorage(path)
    store.create_map("m", {"name": "m"}, "t0")
    _append(store, _payload(BIG, 1))
    kept = _files(path)
    orphan = PayloadFiles(payload_directory(path)).write(b"written, then the process died before its commit")
    store.close()
    reopened = SqliteStorage(path)
    assert orphan not in _files(path) and _files(path) == kept
    assert reopened.load_map("m").batches == [(1, _payload(BIG, 1))]  # type: ignore[union-attr]
    reopened.close()


@pytest.mark.parametrize("damage", ["flipped", "missing", "outside"])
def test_a_damaged_or_missing_file_is_damage_of_its_batch(store: SqliteStorage, path: Path, damage: str) -> None:
    _append(store, _payload(BIG, 1))
    (file,) = _files(path)
    target = payload_directory(path) / file
    if damage == "flipped":
        data = bytearray(target.read_bytes())
        data[1000] ^= 4
        target.write_bytes(bytes(data))
        expected = "its stored batch 1 fails its checksum"
    elif damage == "missing":
        target.unlink()
        expected = f"its stored batch 1: payload file {file} is missing"
    else:  # a row that names a file elsewhere: never read
        (path.parent / "secret").write_bytes(_payload(BIG, 1))
        with sqlite3.connect(path) as db:
            db.execute("UPDATE batches SET file = '../secret'")
        expected = "its stored batch 1: payload file '../secret' is not a name the store gives"
    stored = store.load_map("m")
    assert stored is not None and len(stored.damage) == 1 and stored.damage[0].startswith(expected)


def test_a_payload_file_that_cannot_be_written_stores_nothing(store: SqliteStorage, path: Path) -> None:
    directory = payload_directory(path)
    directory.write_bytes(b"")  # the directory's name taken by a file: every write to it fails
    with pytest.raises(StorageUnavailable, match="payload file could not be written"):
        _append(store, _payload(BIG, 1))
    assert _append(store, b"small") == 1  # the store goes on; the failed batch took no version
    directory.unlink()
    assert _append(store, _payload(BIG, 2)) == 2


def _hold_big_writes(monkeypatch: pytest.MonkeyPatch) -> tuple[threading.Event, threading.Event]:
    """Hold every payload file write until ``release`` is set; ``writing`` is set once one has begun."""
    writing, release = threading.Event(), threading.Event()
    write = PayloadFiles.write

    def held(self: PayloadFiles, payload: bytes) -> str:
        writing.set()
        assert release.wait(30)
        return write(self, payload)

    monkeypatch.setattr(PayloadFiles, "write", held)
    return writing, release


def test_small_commits_go_on_while_a_big_payload_is_written(store: SqliteStorage,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    store.create_map("other", {"name": "other"}, "t0")
    writing, release = _hold_big_writes(monkeypatch)
    big = threading.Thread(target=_append, args=(store, _payload(BIG, 1)))
    big.start()
    try:
        assert writing.wait(30)
        assert [_append(store, b"small", "other") for _ in range(3)] == [1, 2, 3]  # not behind the big write
    finally:
        release.set()
        big.join()
    assert [v for v, _ in store.load_map("m").batches] == [1]  # type: ignore[union-attr]


def test_the_committer_commits_a_big_batch_beside_the_group(store: SqliteStorage,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    store.create_map("other", {"name": "other"}, "t0")
    writing, release = _hold_big_writes(monkeypatch)
    committer = GroupCommitter(store, Metrics())
    try:
        big = committer.append(BatchRecord("m", None, _payload(BIG, 1), "t", 1))
        assert writing.wait(30)
        small = [committer.append(BatchRecord("other", None, b"s%d" % k, "t", 1)) for k in range(3)]
        assert [f.result(timeout=30) for f in small] == [1, 2, 3] and not big.done()
        release.set()
        assert big.result(timeout=30) == 1
    finally:
        release.set()
        committer.shutdown()


def test_a_backup_is_one_self_contained_file(store: SqliteStorage, path: Path, tmp_path: Path) -> None:
    for k in range(3):
        _append(store, _payload(BIG, k))
    store.write_snapshot("m", 2, _payload(BIG, 10))
    assert store.write_base("m", 1, _payload(BIG, 20))
    copy = tmp_path / "copy" / "fuzzyrisk.sqlite3"
    copy.parent.mkdir()
    assert backup(path.parent, copy) > 0
    assert _rows(copy, "SELECT count(*) FROM batches WHERE file IS NOT NULL UNION ALL "
                       "SELECT count(*) FROM snapshots WHERE file IS NOT NULL UNION ALL "
                       "SELECT count(*) FROM bases WHERE file IS NOT NULL") == [(0,), (0,), (0,)]
    restored = SqliteStorage(copy)
    stored, history = restored.load_map("m"), restored.load_history("m")
    restored.close()
    assert stored is not None and stored.damage == [] and stored.snapshot == _payload(BIG, 10)
    assert stored.batches == [(3, _payload(BIG, 2))]
    assert history is not None and history.damage == [] and history.snapshot == _payload(BIG, 20)
    assert history.batches == [(2, _payload(BIG, 1)), (3, _payload(BIG, 2))]


def test_a_backup_taken_while_big_batches_commit_and_snapshots_drop_them_is_complete(
        store: SqliteStorage, path: Path, tmp_path: Path) -> None:
    done = threading.Event()
    acknowledged: list[int] = []

    def writer() -> None:  # batches, each one folded at once (a budget of 0): files come and go under the backup
        k = 0
        while not done.is_set():
            k += 1
            acknowledged.append(_append(store, _payload(BIG, k)))
            if k % 2 == 0:
                store.write_snapshot("m", acknowledged[-1] - 1, _payload(BIG, 1000 + k))
                store.write_base("m", acknowledged[-1] - 1, None)

    thread = threading.Thread(target=writer)
    thread.start()
    copies = []
    try:
        for attempt in range(4):
            copy = tmp_path / f"copy{attempt}" / "fuzzyrisk.sqlite3"
            copy.parent.mkdir()
            before = len(acknowledged)
            backup(path.parent, copy)
            copies.append((copy, before))
    finally:
        done.set()
        thread.join()
    for copy, before in copies:
        restored = SqliteStorage(copy)
        stored = restored.load_map("m")
        restored.close()
        assert stored is not None and stored.damage == []
        assert stored.version >= before  # every batch acknowledged before the backup began
        assert _files(copy) == []  # everything is in the copy's rows


@pytest.mark.parametrize("when", ["_open_named", "_copy_pages"])
def test_a_backup_keeps_the_files_a_snapshot_removes_while_it_copies(store: SqliteStorage, path: Path,
                                                                     tmp_path: Path, when: str,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import app.storage.backup

    for k in range(3):
        _append(store, _payload(BIG, k))
    real = getattr(app.storage.backup, when)

    def then_snapshot(*args: Any) -> Any:  # the service snapshots and folds batches 1-3: their files go
        result = real(*args)
        store.write_snapshot("m", 3, _payload(BIG, 10))
        store.write_base("m", 3, None)
        _append(store, _payload(BIG, 4))
        return result

    monkeypatch.setattr(app.storage.backup, when, then_snapshot)
    target = tmp_path / "copy" / "fuzzyrisk.sqlite3"
    target.parent.mkdir()
    backup(path.parent, target)
    assert len(_files(path)) == 2  # the base's and batch 4's: batches 1-3's files are gone
    restored = SqliteStorage(target)
    stored = restored.load_map("m")
    restored.close()
    # the copy is of the database as the backup began (its pages copied in the transaction that opened the files)
    assert stored is not None and stored.damage == [] and stored.snapshot is None
    assert stored.batches == [(k + 1, _payload(BIG, k)) for k in range(3)]


def test_a_backup_whose_files_a_snapshot_removes_before_it_opens_them_starts_again(
        store: SqliteStorage, path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for k in range(3):
        _append(store, _payload(BIG, k))
    real_open = PayloadFiles.open
    snapshotted: list[bool] = []

    def open_after_a_snapshot(self: PayloadFiles, name: str) -> Any:
        if not snapshotted:  # between the backup's read of the rows and its opening of their files
            snapshotted.append(True)
            store.write_snapshot("m", 3, _payload(BIG, 10))
            store.write_base("m", 3, None)
        return real_open(self, name)

    monkeypatch.setattr(PayloadFiles, "open", open_after_a_snapshot)
    target = tmp_path / "copy" / "fuzzyrisk.sqlite3"
    target.parent.mkdir()
    backup(path.parent, target)
    restored = SqliteStorage(target)
    stored = restored.load_map("m")
    restored.close()
    assert stored is not None and stored.damage == [] and stored.version == 3
    assert stored.snapshot is not None and stored.batches == []


def test_a_backup_of_a_store_missing_a_payload_file_fails_and_leaves_no_copy(store: SqliteStorage, path: Path,
                                                                           tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli.backup import main

    _append(store, _payload(BIG, 1))
    (payload_directory(path) / _files(path)[0]).unlink()
    target = tmp_path / "copy.sqlite3"
    assert main([str(target), "--data-dir", str(path.parent)]) == 1
    assert "so its maps ['m'] are damaged" in capsys.readouterr().err
    assert list(tmp_path.glob("copy.sqlite3*")) == []


def test_a_second_store_on_the_database_leaves_the_first_ones_files_alone(store: SqliteStorage, path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    writing, release = threading.Event(), threading.Event()
    written: list[str] = []
    write = PayloadFiles.write

    def held_after(self: PayloadFiles, payload: bytes) -> str:  # the file is there, its row not yet
        written.append(write(self, payload))
        writing.set()
        assert release.wait(30)
        return written[-1]

    monkeypatch.setattr(PayloadFiles, "write", held_after)
    big = threading.Thread(target=_append, args=(store, _payload(BIG, 1)))
    big.start()
    try:
        assert writing.wait(30)
        second = SqliteStorage(path)  # an overlapping restart, say: it must not sweep that file
        assert len(written) == 1 and _files(path) == written
    finally:
        release.set()
        big.join()
    stored = second.load_map("m")
    second.close()
    assert stored is not None and stored.damage == [] and stored.batches == [(1, _payload(BIG, 1))]


def test_an_unreadable_payload_file_is_damage_of_its_map_not_a_failed_load(store: SqliteStorage, path: Path) -> None:
    _append(store, _payload(BIG, 1))
    (file,) = _files(path)
    (payload_directory(path) / file).unlink()
    (payload_directory(path) / file).mkdir()  # reading it fails (IsADirectoryError), as an I/O error would
    stored = store.load_map("m")
    assert stored is not None and len(stored.damage) == 1 and f"payload file {file} cannot be read" in stored.damage[0]


class _DiskFailsAtCommit:
    """The store's connection, with the disk failing at the next COMMIT as an fsync error does (SQLite's own
    errors can only be had from a failing device, so the COMMIT's is raised here)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __getattr__(self, name: str) -> Any:
        return getattr(self._db, name)

    def execute(self, sql: str, *args: Any) -> Any:
        if sql == "COMMIT":
            self._db.execute("ROLLBACK")
            error = sqlite3.OperationalError("disk I/O error")
            error.sqlite_errorname = "SQLITE_IOERR_FSYNC"  # type: ignore[attr-defined]
            error.sqlite_errorcode = sqlite3.SQLITE_IOERR_FSYNC  # type: ignore[attr-defined]
            raise error
        return self._db.execute(sql, *args)


def test_a_commit_cut_short_by_the_disk_is_uncertain_and_keeps_its_file(path: Path) -> None:
    # its log frames may be on disk, and a recovery after a crash may bring its row back: the file stays for that
    # row (or for the next open's sweep), and the service says the batch may be stored rather than "not stored"
    store = SqliteStorage(path)
    store.create_map("m", {"name": "m"}, "t0")
    db = store._db
    store._db = _DiskFailsAtCommit(db)  # type: ignore[assignment]
    try:
        with pytest.raises(CommitUncertain, match="SQLITE_IOERR_FSYNC, at the commit"):
            _append(store, _payload(BIG, 1))
    finally:
        store._db = db
    assert len(_files(path)) == 1
    assert _append(store, _payload(BIG, 2)) == 1  # the store goes on (the first took no version here)
    assert len(_files(path)) == 2
    store.close()
    reopened = SqliteStorage(path)  # its row is not there: its file is swept
    assert len(_files(path)) == 1 and reopened.load_map("m").batches == [(1, _payload(BIG, 2))]  # type: ignore[union-attr]
    reopened.close()


def test_a_load_reads_its_payload_files_without_holding_the_commits(store: SqliteStorage, path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    # an MCAP export reads up to 256 MiB of a map's log: under the store's lock, every map's commits waited for it
    store.create_map("other", {"name": "other"}, "t0")
    for k in range(3):
        _append(store, _payload(BIG, k))
    reading, release = threading.Event(), threading.Event()
    prefetch = Prefetched.__init__

    def held(self: Prefetched, *args: Any) -> None:
        reading.set()
        assert release.wait(30)
        prefetch(self, *args)

    monkeypatch.setattr(Prefetched, "__init__", held)
    loaded: list[Any] = []
    load = threading.Thread(target=lambda: loaded.append(store.load_map("m")))
    load.start()
    try:
        assert reading.wait(30)
        assert _append(store, b"small", "other") == 1  # not behind the read
        store.write_snapshot("m", 2, _payload(BIG, 10))  # and batches 1-2's files go before they are read
    finally:
        release.set()
        load.join()
    (stored,) = loaded
    # the rows as they are once the files are read: the new snapshot (read from its file then) and batch 3
    assert stored.damage == [] and (stored.snapshot_version, stored.snapshot) == (2, _payload(BIG, 10))
    assert stored.batches == [(3, _payload(BIG, 2))]


def test_a_backup_raises_its_open_file_limit_to_hold_every_payload_file(store: SqliteStorage, path: Path,
                                                                        tmp_path: Path) -> None:
    # every file stays open until its bytes are in the copy: a store's thousands of files met a soft limit of 1,024
    import resource

    for k in range(40):
        _append(store, _payload(BIG, k))
    saved = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (64, saved[1]))  # fewer than the files and the databases need
    try:
        target = tmp_path / "copy.sqlite3"
        backup(path.parent, target)
        assert resource.getrlimit(resource.RLIMIT_NOFILE)[0] >= 40 + 64
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, saved)
    restored = SqliteStorage(target)
    stored = restored.load_map("m")
    restored.close()
    assert stored is not None and stored.damage == [] and len(stored.batches) == 40
