"""CI-sized replica kills (``bench/bench_faults.py --replicas 2`` at 4 kills): two real replica processes on
one PostgreSQL database.

Writers post batches for the same maps through both replicas; one replica at a time is killed -9 at a
random moment and restarted. Nothing acknowledged is lost (the database's log holds every acknowledged
batch under its version, as sent), the replicas never answer one version differently, every read equals
the replay of the log up to its version (no half-applied batch), and the survivor answers reads of every
map right after the kill.

The database is the session's PostgreSQL (``postgres_server``, fsync off: the kills are of the
replicas, not of the database or the machine).
"""

from __future__ import annotations

from typing import Any

import pytest

from bench.bench_faults import ReplicaKillCounts, replica_kill_loop

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

KILLS = 4
#: The issue's target: the survivor answers a read of a map within 1 s of the other replica's kill -9. Asserted
#: as it is, per kill, on the first read (reads never wait for the dead replica: no lock of its transactions
#: is on their path, and its batches are read from the database); measured on the 2-core machine, with both
#: replicas, PostgreSQL, 3 writers and a reader sharing the cores and other work beside (load average 6.5):
#: at most 0.42 s. Reading all 3 maps in turn gets 3 times that bound, which is generous on purpose: every
#: map's first read after a kill may catch up with the batches the dead replica committed, and each of the
#: three reads competes with the writers for the 2 cores (measured: at most 0.5 s).
SURVIVOR_BOUND_S = 1.0

@pytest.fixture(scope="module")
def killed(postgres_server: Any) -> ReplicaKillCounts:
    return replica_kill_loop(KILLS, seed=3, database_url=postgres_server.create_database(), log=lambda _line: None,
                             up_s=(0.5, 1.5), down_s=(0.3, 0.8))


def test_every_kill_was_followed_by_a_restart_and_both_replicas_took_batches(killed: ReplicaKillCounts) -> None:
    assert killed.kills == KILLS, killed.details
    assert killed.server_failed_to_start == 0
    assert killed.batches_acked >= 10 * KILLS
    assert len(killed.committed_by) == 2, killed.committed_by  # each replica committed batches of the maps
    assert len(killed.snapshots_by) == 2, killed.snapshots_by  # and wrote snapshots the other then loaded


def test_no_acknowledged_batch_is_lost_or_stored_otherwise(killed: ReplicaKillCounts) -> None:
    assert killed.acked_lost == 0, killed.details
    assert killed.acked_wrong_content == 0, killed.details
    assert killed.duplicate_versions == 0, killed.unexpected
    assert killed.version_gaps == 0, killed.details
    # a version nobody acknowledged is a batch whose request the kill cut (committed before the replica died)
    assert killed.unexplained_versions == 0, killed.details


def test_replicas_never_diverge(killed: ReplicaKillCounts) -> None:
    assert killed.versions_read_by_both >= 3  # at least the final read of each map, through both replicas
    assert killed.divergent == 0, killed.details


def test_no_half_applied_batch_every_read_is_the_replay_of_the_log(killed: ReplicaKillCounts) -> None:
    assert killed.reads_checked >= 3 * 2 * (KILLS + 1)  # the survivors', the restarted replica's, the final ones
    assert killed.half_applied == 0, killed.details
    assert killed.store_replay_mismatch == 0, killed.details


def test_the_survivor_answers_reads_within_a_second_of_the_kill(killed: ReplicaKillCounts) -> None:
    assert len(killed.survivor_first_read_s) == len(killed.survivor_read_s) == KILLS
    assert max(killed.survivor_first_read_s) <= SURVIVOR_BOUND_S, killed.survivor_first_read_s
    assert max(killed.survivor_read_s) <= 3 * SURVIVOR_BOUND_S, killed.survivor_read_s
    assert killed.acked_while_one_down > 0  # and it took writes meanwhile


def test_no_unexpected_answer_and_no_error_logged(killed: ReplicaKillCounts) -> None:
    assert killed.unexpected == []
    assert killed.server_log_errors == []
