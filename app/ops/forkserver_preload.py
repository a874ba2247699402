"""Imported first by the planner workers' forkserver (``app.ops.forkserver.FORKSERVER_PRELOAD``): it dies with the server.

The server starts the forkserver, the forkserver forks the planner workers, and each worker holds
the pipe on which the forkserver waits for its clients to go. So when the server is killed
(``kill -9``, the OOM killer), the forkserver waits for the workers and the workers wait for work,
forever. Here the forkserver asks Linux to kill it when the server ends (``PR_SET_PDEATHSIG``), and
each worker asks the same of the forkserver (``app.plans.worker.init_worker``); the resource tracker then
sees its last client go and exits by itself.

The import acts only inside a forkserver's preload (anywhere else it does nothing).
"""

from __future__ import annotations

import sys

from app.ops.process_setup import die_with_parent


def _in_forkserver_preload() -> bool:
    """Is this import made by ``multiprocessing.forkserver.main``, i.e. in a forkserver before it serves?"""
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_globals.get("__name__") == "multiprocessing.forkserver" and frame.f_code.co_name == "main":
            return True
        frame = frame.f_back
    return False


ACTIVE = _in_forkserver_preload() and die_with_parent()
