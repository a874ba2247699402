"""Replicas of the service on one PostgreSQL database, as real processes.

A small API for the benchmarks that run a fleet (``bench/bench_faults.py --replicas``, and any
other that wants one):

* :func:`durable_postgres`: ``bench._postgres.running_postgres()`` with ``fsync``,
  ``full_page_writes`` and ``synchronous_commit`` ON (the tests' cluster turns them off), for
  benchmarks whose figures include the database's commits.
* :class:`Replicas`: ``count`` ``python -m app`` processes (``bench._client.ServerProcess``:
  own process group, own free port, own data directory kept across restarts) with the same
  ``FUZZYRISK_DATABASE_URL``. ``start()`` (all at once), ``urls``, ``kill(i)`` (SIGKILL),
  ``restart(i)`` (same data directory, a new port), ``error_lines()``, ``close()``; a context
  manager.

Every process a :class:`Replicas` starts is ended by ``close()`` (also on ``__exit__``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Self

import psycopg

from bench import _postgres
from bench._client import ServerProcess
from bench._postgres import PostgresServer

#: Replica i connects as ``application_name`` ``fuzzyrisk-replica-<i>`` (``pg_stat_activity``; a trigger can tell
#: which replica wrote a row by ``current_setting('application_name')``).
APPLICATION_NAME = "fuzzyrisk-replica-"
#: What ``durable_postgres`` changes in the tests' cluster settings (``bench._postgres.SETTINGS``).
DURABLE_SETTINGS = {"fsync": "on", "full_page_writes": "on", "synchronous_commit": "on"}


@contextmanager
def durable_postgres() -> Iterator[PostgresServer]:
    """A throwaway PostgreSQL cluster that flushes its commits to disk, as a user's does (the tests' cluster
    does not); its settings are checked with ``SHOW`` once it runs (``RuntimeError`` if it lacks them)."""
    server = PostgresServer(settings={**_postgres.DURABLE, **DURABLE_SETTINGS})
    try:
        server.start()
        with psycopg.connect(server.url(), autocommit=True) as conn:
            for key, wanted in DURABLE_SETTINGS.items():
                (value,) = conn.execute(f"SHOW {key}").fetchone() or ("?",)
                if value != wanted:
                    raise RuntimeError(f"PostgreSQL runs with {key}={value}, not {wanted}")
        yield server
    finally:
        server.stop()


class Replicas:
    """``count`` replicas of the service sharing the database at ``database_url``.

    ``env``: extra ``FUZZYRISK_*`` variables for every replica (``FUZZYRISK_DATABASE_URL`` is set
    here, with ``application_name=fuzzyrisk-replica-<i>`` added to the URL). ``servers[i]`` is
    replica i's :class:`ServerProcess`; its data directory (numba cache, plan grids) is its own
    and survives ``kill``/``restart``.
    """

    def __init__(self, count: int, database_url: str, env: Mapping[str, str] | None = None) -> None:
        assert count >= 1
        self.database_url = database_url
        joiner = "&" if "?" in database_url else "?"
        self.servers = [
            ServerProcess(env={**(env or {}),
                               "FUZZYRISK_DATABASE_URL": f"{database_url}{joiner}application_name={APPLICATION_NAME}{i}"})
            for i in range(count)
        ]

    def __len__(self) -> int:
        return len(self.servers)

    @property
    def urls(self) -> list[str]:
        """Each replica's base URL (``http://127.0.0.1:PORT``; the port changes at a restart)."""
        return [server.url for server in self.servers]

    def start(self, timeout_s: float = 180.0) -> Self:
        """Start every replica at once and wait for each one's ``/health``; ``RuntimeError`` (log tail) if one fails."""
        with ThreadPoolExecutor(len(self.servers)) as pool:
            for future in [pool.submit(server.start, timeout_s) for server in self.servers]:
                future.result()
        return self

    def kill(self, i: int) -> None:
        """SIGKILL replica ``i`` and its process group (no flush, no snapshot)."""
        self.servers[i].kill()

    def restart(self, i: int, timeout_s: float = 120.0) -> float:
        """Start replica ``i`` again on its data directory (after ``kill``); the seconds until ``/health`` answered."""
        started = time.perf_counter()
        self.servers[i].start(timeout_s)
        return time.perf_counter() - started

    def error_lines(self, chars: int = 600) -> list[str]:
        """The ``level=ERROR``/``CRITICAL`` records of every replica's log so far, prefixed ``replica i:``
        (each cut to its last ``chars`` characters). The log format must be ``kv`` (``ServerProcess``'s default)."""
        out = []
        for i, server in enumerate(self.servers):
            for line in server.log_tail(10**8).splitlines():
                if "level=ERROR" in line or "level=CRITICAL" in line:
                    out.append(f"replica {i}: {line[-chars:]}")
        return out

    def close(self) -> None:
        """Kill every replica and remove its temporary directory (log and data)."""
        for server in self.servers:
            server.close()

    def __enter__(self) -> Self:
        try:
            return self.start()
        except BaseException:
            self.close()  # the replicas that did start
            raise

    def __exit__(self, *exc: object) -> None:
        self.close()
