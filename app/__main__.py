"""`python -m app`: serve the product (options override the FUZZYRISK_* environment).

The order matters: settings first (one that needs an optional extra not installed: exit 2 at once),
and logs; then the port (taken: exit 1 at once), the directories (numba's kernel cache must be set
before numba is imported) and BLAS's threads (before numpy is); then the application, whose lifespan
loads the maps before uvicorn listens, and compiles the kernels and starts the planner workers in the
background (``GET /ready`` says when they are done).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from pydantic import ValidationError

from app.config import Settings
from app.ops.process_setup import (
    GIL_SWITCH_INTERVAL_S,
    StartupError,
    bind,
    limit_blas_threads,
    missing_extra,
    prepare_directories,
)
from app.ops.logs import configure_logging
from app.ops.version import add_version_option

#: Exit status when the service cannot start (a bad setting, a port in use, an unusable data directory).
EXIT_STARTUP_FAILURE = 1
#: Exit status when a setting needs an optional extra that is not installed (what this install cannot do was asked).
EXIT_MISSING_EXTRA = 2


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m app", description="fuzzyrisk: fuzzy occupancy maps and risk-bounded plans over HTTP")
    parser.add_argument("--host", help="interface to listen on (FUZZYRISK_HOST, default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="TCP port (FUZZYRISK_PORT, default 8000)")
    parser.add_argument("--data-dir", type=Path, help="map database directory (FUZZYRISK_DATA_DIR, default ./data)")
    add_version_option(parser)
    args = parser.parse_args(argv)
    overrides = {k: v for k, v in vars(args).items() if v is not None}
    try:
        settings = Settings(**overrides)
    except ValidationError as exc:
        sys.exit(f"python -m app: invalid configuration:\n{exc}")
    if needed := missing_extra(settings):  # before anything binds or is created: nothing to undo
        print(f"python -m app: {needed}", file=sys.stderr)
        sys.exit(EXIT_MISSING_EXTRA)
    configure_logging(log_format=settings.log_format, level=settings.log_level)
    log = logging.getLogger("fuzzyrisk")
    try:
        sock = bind(settings.host, settings.port)
        directories = prepare_directories(settings)
        limit_blas_threads()  # before numpy is imported, below
    except StartupError as exc:
        log.error("cannot start: %s", exc)
        sys.exit(EXIT_STARTUP_FAILURE)
    if directories.warning:
        log.warning(directories.warning)
    if settings.api_key is None and settings.host not in ("127.0.0.1", "localhost", "::1"):
        log.warning("listening on %s without FUZZYRISK_API_KEY: anyone who can reach it can change maps", settings.host)
    log.info(
        "starting",
        extra={"fields": {"host": settings.host, "port": settings.port, "data_dir": str(settings.data_dir.resolve()),
                          "auth": settings.api_key is not None, "kernel_cache": str(directories.numba_cache)}},
    )

    # numba, OMPL, the web stack: imported only now that NUMBA_CACHE_DIR is set
    import uvicorn

    from app.api import httpserver
    from app.api.factory import create_app

    server = uvicorn.Server(uvicorn.Config(
        create_app(settings),
        http=httpserver.protocol(settings.header_timeout_s),  # h11 with a deadline on request headers
        log_config=None,  # keep our structured handler
        access_log=False,  # one access record per request comes from our middleware
        timeout_graceful_shutdown=settings.graceful_timeout_s,
    ))
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    server.run(sockets=[sock])
    if not server.started:  # the lifespan failed (it logged why)
        sys.exit(EXIT_STARTUP_FAILURE)


if __name__ == "__main__":
    main()
