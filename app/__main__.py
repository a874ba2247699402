"""`python -m app`: serve the product (options override the FUZZYRISK_* environment)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import uvicorn

from app.config import Settings
from app.logs import configure_logging
from app.main import create_app


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m app", description="fuzzyrisk: fuzzy occupancy maps and risk-bounded plans over HTTP")
    parser.add_argument("--host", help="interface to listen on (FUZZYRISK_HOST, default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="TCP port (FUZZYRISK_PORT, default 8000)")
    parser.add_argument("--data-dir", type=Path, help="map database directory (FUZZYRISK_DATA_DIR, default ./data)")
    args = parser.parse_args(argv)
    overrides = {k: v for k, v in vars(args).items() if v is not None}
    settings = Settings(**overrides)
    configure_logging(log_format=settings.log_format, level=settings.log_level)
    log = logging.getLogger("fuzzyrisk")
    if settings.api_key is None and settings.host not in ("127.0.0.1", "localhost", "::1"):
        log.warning("listening on %s without FUZZYRISK_API_KEY: anyone who can reach it can change maps", settings.host)
    log.info(
        "starting",
        extra={"fields": {"host": settings.host, "port": settings.port, "data_dir": str(settings.data_dir.resolve()),
                          "auth": settings.api_key is not None}},
    )
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_config=None,  # keep our structured handler
        access_log=False,  # one access record per request comes from our middleware
        timeout_graceful_shutdown=settings.graceful_timeout_s,
    )


if __name__ == "__main__":
    main()
