"""CI-sized crash and storage faults (``bench/bench_faults.py`` at 5 kills): real server processes.

kill -9 at random moments during a stream of batches, then restart: no acknowledged batch
lost, every map loads, no half-applied batch, risk bit-identical to an in-process replay of
the acknowledged batches. A full disk and a read-only data directory: a 5xx with a JSON
error body, no batch applied that was refused, nothing corrupted, recovery once writable.
"""

from __future__ import annotations

import pytest

from bench.bench_faults import KillCounts, StorageReport, kill_loop, storage_faults

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

KILLS = 5


@pytest.fixture(scope="module", params=["sqlite", "postgres"])
def killed(request: pytest.FixtureRequest) -> KillCounts:
    """The kill loop with the maps in SQLite, then in PostgreSQL (one replica: a fleet's replicas are
    ``test_replica_kills``)."""
    url = request.getfixturevalue("postgres_server").create_database() if request.param == "postgres" else None
    return kill_loop(KILLS, seed=3, log=lambda _line: None, max_delay_s=1.0, database_url=url)


@pytest.fixture(scope="module")
def storage() -> StorageReport:
    return storage_faults(seed=3, log=lambda _line: None)


def test_every_kill_was_followed_by_a_restart(killed: KillCounts) -> None:
    assert killed.kills == KILLS, killed
    assert killed.server_failed_to_start == 0, killed
    assert killed.batches_acked >= KILLS  # the stream ran between the kills


def test_no_acknowledged_batch_is_lost_across_kill_9(killed: KillCounts) -> None:
    assert killed.acked_lost == 0, killed
    assert killed.version_jumps == 0, killed


def test_every_map_loads_after_kill_9(killed: KillCounts) -> None:
    assert killed.maps_failed_to_load == 0, killed


def test_no_batch_is_half_applied_and_risk_matches_the_replay(killed: KillCounts) -> None:
    assert killed.half_applied == 0, killed
    assert killed.risk_mismatches == 0, killed
    assert killed.other_errors == [], killed


def test_full_disk_answers_a_5xx_with_a_detail(storage: StorageReport) -> None:
    assert 500 <= storage.disk_full_status < 600, storage.disk_full_body
    assert storage.disk_full_json_detail, storage.disk_full_body
    # keep knocking: every answer stays clean. A 200 is one too: a full disk is not monotonic (what a
    # refused write took is given back, and a smaller batch can fit); it is acknowledged, and the map
    # is checked with it
    statuses = storage.statuses_while_full
    assert all(status == 200 or 500 <= status < 600 for status in statuses), statuses
    assert sum(n for status, n in statuses.items() if status >= 500) >= 3, statuses


def test_full_disk_applies_no_refused_batch_and_corrupts_nothing(storage: StorageReport) -> None:
    assert storage.refused_but_applied == 0
    assert storage.map_intact_while_full, storage.map_note_while_full
    assert storage.restart_after_full_ok, storage.restart_after_full_note


def test_a_map_can_be_deleted_while_the_disk_is_full(storage: StorageReport) -> None:
    # DELETE answered 503 on a full disk, so space could not be freed through the API
    assert storage.delete_while_full.startswith("204"), storage.delete_while_full


def test_service_writes_again_once_space_is_back(storage: StorageReport) -> None:
    assert storage.recovered_after_space, storage.recovered_status


def test_read_only_data_dir_serves_reads_and_refuses_writes_cleanly(storage: StorageReport) -> None:
    assert storage.ro_restart.startswith("started"), storage.ro_restart
    assert storage.ro_reads_ok
    assert 500 <= storage.ro_status < 600 and storage.ro_json_detail, storage.ro_body
    assert storage.ro_final_ok, storage.ro_final_note
    assert storage.other == []
