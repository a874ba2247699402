"""A real PostgreSQL server for the tests and benchmarks: a throwaway cluster.

Its binaries (``initdb``, ``postgres``) come from ``$FUZZYRISK_TEST_PG_BINDIR``, else the
newest ``/usr/lib/postgresql/*/bin`` (Debian's ``postgresql`` package), else the PATH. The
cluster lives in a temporary directory, listens on 127.0.0.1 at a free port and on a unix
socket in that directory, trusts every local connection, and is stopped and removed at the
end. As root it runs as the ``postgres`` user (PostgreSQL refuses to run as root).

The tests' fixture is ``tests.pgserver.postgres_server``; a benchmark uses ``running_postgres()``.
"""

from __future__ import annotations

import ctypes
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import psutil
import psycopg

import dev

INSTALL_HINT = ("PostgreSQL's server binaries (initdb, postgres) are needed: `python3 dev.py test` installs Debian's "
                "postgresql (or `apt-get install postgresql`), or set FUZZYRISK_TEST_PG_BINDIR to their directory")
SUPERUSER = "postgres"
#: Cluster settings for tests: nothing here is about surviving a power cut, so no fsync.
SETTINGS = {"fsync": "off", "full_page_writes": "off", "max_connections": "200", "shared_buffers": "32MB"}
#: For benchmarks: PostgreSQL's durable defaults (fsync and synchronous commit on), so that a commit costs what
#: it costs a user.
DURABLE = {"max_connections": "200", "shared_buffers": "128MB"}


class PostgresNotFound(RuntimeError):
    """No PostgreSQL server binaries on this machine."""


def find_bindir() -> Path:
    """The directory holding ``initdb`` and ``postgres`` (``dev.find_pg_bindir``); ``PostgresNotFound`` (with how to
    install them)."""
    found = dev.find_pg_bindir()
    if found is None:
        looked = ", ".join(map(str, dev.pg_bindir_candidates())) or "nothing found"
        raise PostgresNotFound(f"{INSTALL_HINT} (looked in: {looked})")
    return found


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


try:
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl  # looked up here, not in the forked child
except (OSError, AttributeError):
    _PRCTL = None  # not Linux: the session's teardown still stops the server


def _die_with_parent() -> None:
    """In the server's process before exec: end it (SIGQUIT: immediate shutdown) should the test process die."""
    if _PRCTL is not None:
        _PRCTL(1, signal.SIGQUIT)  # PR_SET_PDEATHSIG


class PostgresServer:
    """One throwaway cluster: ``start()``, ``url(dbname)``, ``create_database()``, ``stop()``."""

    def __init__(self, bindir: Path | None = None, settings: dict[str, str] | None = None) -> None:
        self.bindir = bindir or find_bindir()
        self.settings = SETTINGS if settings is None else settings
        self.root = Path(tempfile.mkdtemp(prefix="fuzzyrisk-pg-"))
        self.data = self.root / "data"
        self.log = self.root / "postgres.log"
        self.port = 0
        self._process: subprocess.Popen[bytes] | None = None
        self._user: dict[str, Any] = {}
        self._databases = 0
        self._lock = threading.Lock()
        if os.geteuid() == 0:
            # PostgreSQL will not run as root: the cluster's files and processes are the postgres user's
            try:
                account = pwd.getpwnam("postgres")  # Debian's postgresql package makes it
            except KeyError:
                account = pwd.getpwnam("nobody")
            self._user = {"user": account.pw_uid, "group": account.pw_gid, "extra_groups": []}
            os.chown(self.root, account.pw_uid, account.pw_gid)

    def url(self, dbname: str = "postgres") -> str:
        return f"postgresql://{SUPERUSER}@127.0.0.1:{self.port}/{dbname}"

    def start(self) -> None:
        try:
            subprocess.run([str(self.bindir / "initdb"), "-D", str(self.data), "-A", "trust", "-U", SUPERUSER,
                            "-E", "UTF8", "--locale=C", "--no-sync"], check=True, capture_output=True,
                           cwd=self.root, **self._user)
        except subprocess.CalledProcessError as exc:
            raise RuntimeError(f"initdb failed: {exc.stderr.decode(errors='replace')}") from exc
        for _ in range(3):  # the free port may be taken by someone else before the server binds it
            self.port = _free_port()
            options = [f"-c{key}={value}" for key, value in
                       {**self.settings, "listen_addresses": "127.0.0.1", "port": str(self.port),
                        "unix_socket_directories": str(self.root)}.items()]
            with open(self.log, "ab") as log:
                self._process = subprocess.Popen([str(self.bindir / "postgres"), "-D", str(self.data), *options],
                                                 stdin=subprocess.DEVNULL, stdout=log, stderr=log, cwd=self.root,
                                                 preexec_fn=_die_with_parent,  # noqa: PLW1509 - one foreign call
                                                 **self._user)
            if self._wait_ready(60.0):
                return
            self._end_process()
        raise RuntimeError(f"PostgreSQL did not start; its log:\n{self.log.read_text(errors='replace')[-4000:]}")

    def _wait_ready(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        assert self._process is not None
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                return False
            try:
                psycopg.connect(self.url(), connect_timeout=2).close()
                return True
            except psycopg.OperationalError:
                time.sleep(0.05)
        return False

    def create_database(self) -> str:
        """A new, empty database; its URL."""
        with self._lock:
            self._databases += 1
            name = f"test_{self._databases}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def _end_process(self) -> None:
        process, self._process = self._process, None
        if process is None or process.poll() is not None:
            return
        try:
            children = psutil.Process(process.pid).children(recursive=True)
        except psutil.Error:
            children = []
        # fast shutdown (clients disconnected, a checkpoint), then immediate (the postmaster ends its
        # children itself), then a kill of the postmaster and of the backends it leaves behind
        for stop, wait in ((signal.SIGINT, 30.0), (signal.SIGQUIT, 10.0), (signal.SIGKILL, 10.0)):
            process.send_signal(stop)
            try:
                process.wait(wait)
                break
            except subprocess.TimeoutExpired:
                continue
        _, alive = psutil.wait_procs(children, timeout=10.0)
        for child in alive:
            try:
                child.kill()
            except psutil.Error:
                pass

    def stop(self) -> None:
        """Stop the server (no process of it stays) and remove its directory."""
        try:
            self._end_process()
        finally:
            shutil.rmtree(self.root, ignore_errors=True)


@contextmanager
def running_postgres(*, durable: bool = False) -> Iterator[PostgresServer]:
    """A started server, stopped and removed on exit; ``durable``: with fsync (``DURABLE``), for benchmarks."""
    server = PostgresServer(settings=DURABLE if durable else None)
    try:
        server.start()
        yield server
    finally:
        server.stop()
