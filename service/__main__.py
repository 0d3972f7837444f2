"""``python -m service [--host H] [--port P] [--workers N]``: run the try-on API with uvicorn.

Settings come from the environment (``TRYON_*``, service/config.py); the flags override a few.
SIGTERM drains: uvicorn stops accepting connections, in-flight requests finish (up to
``shutdown_drain_s``), then the worker pool and the job runner stop (running jobs are re-queued).
"""
from __future__ import annotations

import argparse

import uvicorn

from service.app import create_app
from service.config import Settings
from service.logs import configure_logging


def main(argv: list[str] | None = None) -> None:
    defaults = Settings()
    parser = argparse.ArgumentParser(prog="python -m service", description="Run the try-on API.")
    parser.add_argument("--host", default=defaults.host, help="bind address (env TRYON_HOST)")
    parser.add_argument("--port", type=int, default=defaults.port, help="port (env TRYON_PORT)")
    parser.add_argument("--workers", type=int, default=defaults.workers, help="inference workers (env TRYON_WORKERS)")
    parser.add_argument("--log-level", default=defaults.log_level)
    args = parser.parse_args(argv)
    settings = defaults.model_copy(update={"host": args.host, "port": args.port, "log_level": args.log_level, "workers": args.workers})
    configure_logging(args.log_level, settings.log_json)
    uvicorn.run(
        create_app(settings), host=settings.host, port=settings.port, log_level=args.log_level, access_log=False,
        log_config=None, timeout_graceful_shutdown=int(settings.shutdown_drain_s) or None, timeout_keep_alive=5,
    )


if __name__ == "__main__":
    main()
