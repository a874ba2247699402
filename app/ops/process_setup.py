"""What the service's processes need from the operating system, set up before anything else runs.

* ``missing_extra``: a setting that needs an optional extra not installed here stops the start first;
* ``bind``: the listening socket, bound first, so that a port in use stops the start at once;
* ``prepare_directories``: numba's kernel cache and, on a read-only root, the temporary files
  in the data directory (before numba is imported: it reads ``NUMBA_CACHE_DIR`` then);
* ``die_with_parent`` and ``exit_with_parent``: children that end when the server ends, however
  it ends (``kill -9`` included), rather than wait for work that will never come.
"""

from __future__ import annotations

import ctypes
import errno
import importlib.util
import multiprocessing
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

from app.config import Settings

#: prctl(2) option: the signal this process gets when the thread that forked it ends.
PR_SET_PDEATHSIG = 1


class StartupError(Exception):
    """The service cannot start; the message says why and what to change."""


#: How long a thread holding the GIL keeps it while another waits (CPython's default is 5 ms). The event
#: loop waits for the GIL each time it wakes; with a thread parsing a large body or serializing a grid,
#: every wake-up cost up to 5 ms, and a request wakes it several times (bench abuse rows 1, 9, 10).
GIL_SWITCH_INTERVAL_S = 0.001
#: BLAS threads of each of the service's processes. OpenBLAS (numpy's and scipy's) starts one a core and splits
#: every product over them: the rotation of a lidar cloud's 131,072 points (``Rotation.apply``, as a cloud is placed)
#: took 3.1 ms of wall and 3.3 ms of CPU that way, 0.46 ms on one thread, and the extra thread took 22-41 ms of
#: CPU a cloud in the server, on cores the fusion and parse threads already share.
BLAS_THREADS = 1
_BLAS_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass(frozen=True)
class Extra:
    """An optional extra of ``pyproject.toml`` that a setting needs once it is set."""

    name: str  # pip install 'fuzzyrisk[name]'
    setting: str  # the ``Settings`` field
    modules: tuple[str, ...]  # what the extra installs, by import name

    @property
    def variable(self) -> str:
        return f"{Settings.model_config['env_prefix']}{self.setting.upper()}"

    def missing(self) -> list[str]:
        """Its modules that cannot be found here (looked up, not imported: importing is the server's business)."""
        return [module for module in self.modules if importlib.util.find_spec(module) is None]

    def needed(self, what: str) -> str:
        """One line: the setting needs ``what``, and how to install it."""
        return (f"{self.variable} needs {what}, which is not installed: pip install 'fuzzyrisk[{self.name}]' "
                f"(an image: docker build --build-arg EXTRAS={self.name}), or unset {self.variable}")


#: The settings that need an optional extra (the plots, test and bench extras serve no setting).
POSTGRES_EXTRA = Extra("postgres", "database_url", ("psycopg", "psycopg_pool"))
FOXGLOVE_EXTRA = Extra("foxglove", "foxglove_port", ("foxglove",))
EXTRAS = (POSTGRES_EXTRA, FOXGLOVE_EXTRA)


def missing_extra(settings: Settings) -> str | None:
    """The line that stops ``python -m app`` before anything starts when a setting given needs an extra that is not
    installed; None when every such extra is there."""
    for extra in EXTRAS:
        if getattr(settings, extra.setting) is not None and (missing := extra.missing()):
            return extra.needed(", ".join(missing))
    return None


def foxglove_sdk_missing(exc: ImportError) -> StartupError:
    """The error of ``app.reads.foxglove`` imported without the Foxglove SDK (``create_app`` in a process of one's
    own: ``python -m app`` stops before, on ``missing_extra``), in the same words."""
    return StartupError(FOXGLOVE_EXTRA.needed(f"the Foxglove SDK ({exc})"))


def bind(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port`` (not listening yet: uvicorn listens once the maps are loaded).

    Raises ``StartupError`` naming the setting to change when the port is taken or the address unusable.
    Python's sockets are not inherited by child processes, so the planner workers never hold the port.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # IPPROTO_TCP named, not left to the default (0): asyncio turns Nagle's algorithm off (TCP_NODELAY) only
    # on connections of a socket that says it is TCP; with it on, small answers wait ~40 ms for delayed ACKs
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn does: a restart need not wait out TIME_WAIT
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise StartupError(
                f"port {port} on {host} is already in use (another fuzzyrisk, or another service): stop it, or "
                "choose another port with --port or FUZZYRISK_PORT"
            ) from None
        if exc.errno == errno.EACCES:
            raise StartupError(f"not allowed to listen on port {port}: choose a port above 1023 (--port, FUZZYRISK_PORT)"
                               ) from None
        raise StartupError(f"cannot listen on {host}:{port} ({exc.strerror}): check --host / FUZZYRISK_HOST") from None
    return sock


@dataclass(frozen=True)
class Directories:
    """Where this process keeps what it writes besides the map database."""

    numba_cache: Path
    temp: Path | None  # None: the system's temporary directory
    warning: str | None = None  # a fallback taken, for the log


def limit_blas_threads() -> None:
    """``BLAS_THREADS`` for this process and its children, unless the environment sets its own.

    Call before numpy is imported: OpenBLAS reads the variable once, when it is loaded.
    """
    for variable in _BLAS_VARIABLES:
        os.environ.setdefault(variable, str(BLAS_THREADS))


def prepare_directories(settings: Settings) -> Directories:
    """Create the data directory, point numba's kernel cache at ``settings.numba_cache_dir`` and, when the
    system has no writable temporary directory (a read-only root), the temporary files (multiprocessing's
    sockets) at ``<data dir>/tmp``. Child processes inherit both through the environment.

    Call before numba is imported. Raises ``StartupError`` when the data directory cannot be created, or
    when a cache directory set with NUMBA_CACHE_DIR is not writable; a data directory that is (read-only)
    gets the kernels cached in a temporary directory instead, with a warning.
    """
    try:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StartupError(f"cannot create the data directory {settings.data_dir} ({exc.strerror}): choose a "
                           "writable one with --data-dir or FUZZYRISK_DATA_DIR") from None
    temp = _ensure_temp_dir(settings.temp_dir)
    cache, warning = settings.numba_cache_dir, None
    try:
        cache.mkdir(parents=True, exist_ok=True)
        _check_writable(cache)
    except OSError as exc:
        if os.environ.get("NUMBA_CACHE_DIR"):
            raise StartupError(f"NUMBA_CACHE_DIR {cache} is not writable ({exc.strerror}): point it at a "
                               "writable directory, or unset it to cache the kernels in the data directory") from None
        try:
            cache = Path(tempfile.mkdtemp(prefix="fuzzyrisk-numba-"))
        except OSError:
            raise StartupError(f"numba's kernel cache {cache} is not writable ({exc.strerror}) and there is no "
                               "writable temporary directory: set NUMBA_CACHE_DIR to a writable directory") from None
        warning = (f"{settings.numba_cache_dir} is not writable ({exc.strerror}): the kernels are cached in {cache} "
                   "for this run only, so every start compiles them")
    os.environ["NUMBA_CACHE_DIR"] = str(cache.resolve())
    return Directories(numba_cache=cache.resolve(), temp=temp, warning=warning)


def _check_writable(directory: Path) -> None:
    with tempfile.TemporaryFile(dir=directory):
        pass


def _ensure_temp_dir(private_dir: Path) -> Path | None:
    """``private_dir`` (``Settings.temp_dir``: ``<data dir>/tmp``) as TMPDIR when no standard temporary directory
    is writable, else None."""
    tempfile.tempdir = None  # look again: TMPDIR may have changed since the last look
    try:
        chosen: Path | None = Path(tempfile.gettempdir())
    except FileNotFoundError:
        chosen = None
    # tempfile falls back to the working directory when /tmp, /var/tmp and /usr/tmp all refuse a file
    if chosen is not None and chosen != Path.cwd():
        return None
    private = private_dir.resolve()
    shutil.rmtree(private, ignore_errors=True)  # what a killed run left (multiprocessing's sockets)
    private.mkdir(parents=True)
    os.environ["TMPDIR"] = str(private)
    tempfile.tempdir = None
    return private


def die_with_parent() -> bool:
    """Have Linux SIGKILL this process when its parent ends (``PR_SET_PDEATHSIG``); False where it cannot.

    "Parent" is, precisely, the thread that forked this process: the caller's parent must fork it
    from a thread that lives as long as the parent process.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return bool(libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0)
    except (OSError, AttributeError):
        return False


def exit_with_parent() -> None:
    """In a multiprocessing child: a daemon thread that ends this process once its parent process is gone.

    Works everywhere (it waits on the pipe multiprocessing keeps open in the parent), but it needs the GIL
    to act, which a long C++ call may hold; ``die_with_parent`` is the immediate path on Linux.
    """
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        parent.join()  # returns when the parent's end of the pipe closes: the parent has exited
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def lower_priority(by: int) -> None:
    """Run the calling thread (and the threads and processes it starts) ``by`` steps of niceness below where it
    runs now: the CPU goes to the others first.

    Relative, so that a service started niced (``nice``, systemd's ``Nice=``) keeps the order. Linux
    schedules each thread with its own niceness; elsewhere, or where it is not allowed, nothing changes
    (equal shares, as before).
    """
    try:
        me = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, me, min(19, os.getpriority(os.PRIO_PROCESS, me) + by))
    except (AttributeError, OSError):
        pass


def start_worker_process(nice: int) -> None:
    """In a worker process forked by the forkserver: end with the server, and run ``nice`` steps below it."""
    die_with_parent()  # the forkserver, which dies with the server
    exit_with_parent()  # the server itself: other systems, or the forkserver gone before the line above
    lower_priority(nice)


def give_back_freed_memory() -> None:
    """Return the free pages of every malloc arena to the system (glibc's ``malloc_trim``; a no-op elsewhere).

    A map's state is many small blocks, allocated by whichever fusion thread touched them, in that
    thread's arena: freed, they stay with the process. Measured (25 maps of 16 M cells made, a
    scan fused into each, all deleted, six rounds): 0 MiB given back after a round's deletes before, 330-1,120
    MiB with this. It gives back only what is already freed: a map must be freed at its delete, not by a
    later run of the cyclic garbage collector (a map was a reference cycle until 2026-12-02; the process
    then kept up to 400 MiB of deleted maps a round; now 25 maps made and deleted leave it where it began).
    """
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: its allocator has its own policy
        pass
