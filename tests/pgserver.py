"""The tests' PostgreSQL: one throwaway cluster (``bench._postgres``) per session.

Registered in ``tests/conftest.py``; a test asks for ``postgres_server`` and calls ``create_database()``
for a fresh, empty database.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from bench._postgres import PostgresNotFound, PostgresServer, find_bindir

_shared: PostgresServer | None = None
_users = 0


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """A PostgreSQL server for the whole session (``url(dbname)``, ``create_database()``); fails, never skips,
    when PostgreSQL is not installed."""
    global _shared, _users
    # one server even when several conftests (or a conftest and a test module) register the fixture
    server = _shared
    if server is None:
        try:
            bindir = find_bindir()
        except PostgresNotFound as exc:
            missing = str(exc)
        else:
            missing = ""
        if missing:  # failed outside the except block: the message alone, no chained traceback
            pytest.fail(missing, pytrace=False)
        server = PostgresServer(bindir)
        try:
            server.start()
        except BaseException:
            server.stop()
            raise
        _shared = server
    _users += 1
    try:
        yield server
    finally:
        _users -= 1
        if _users == 0:
            _shared = None
            server.stop()
