"""The forkserver that the planner workers and the parse process are forked from, started once.

fork would copy the server's threads and locks into a child; a forkserver forks clean processes that
have already imported what they need (OMPL, numba's kernels, pydantic). It is started from a thread
that lives as long as the server, and ties its life to the server (``app.ops.forkserver_preload``).
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import multiprocessing.context
import multiprocessing.forkserver

#: Modules the forkserver imports before it forks any worker: first the one that ties its life to the
#: server's, then the planner stack (``planning.query`` compiles, or loads, numba's kernels as it is imported),
#: then the parse process's (``app.maps.ingest``: pydantic and the schemas, a second at its first batch otherwise).
FORKSERVER_PRELOAD = ["app.ops.forkserver_preload", "app.plans.worker", "planning.query", "app.maps.ingest"]
# Linux ties the forkserver's death signal to the thread that started it, so that thread must live as long
# as the process: this one never ends before the interpreter does (a request's thread may).
_FORKSERVER_STARTER = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="forkserver-start")


def ensure_forkserver(context: multiprocessing.context.BaseContext) -> None:
    """Start the forkserver (if it is not running) from the long-lived starter thread; blocks."""
    if context.get_start_method() == "forkserver":
        _FORKSERVER_STARTER.submit(multiprocessing.forkserver.ensure_running).result()


def worker_context() -> multiprocessing.context.BaseContext:
    # fork would copy the server's threads and locks into the child; forkserver forks a clean
    # process that has already imported the planner stack
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    context = multiprocessing.get_context(method)
    if method == "forkserver":
        context.set_forkserver_preload(FORKSERVER_PRELOAD)
    return context
