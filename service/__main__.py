"""``python -m service [--host H] [--port P]``: run the try-on API with uvicorn."""
from __future__ import annotations

import argparse
import logging

import uvicorn

from service.app import create_app
from service.config import Settings


def main(argv: list[str] | None = None) -> None:
    defaults = Settings()
    parser = argparse.ArgumentParser(prog="python -m service", description="Run the try-on API.")
    parser.add_argument("--host", default=defaults.host, help="bind address (env TRYON_HOST)")
    parser.add_argument("--port", type=int, default=defaults.port, help="port (env TRYON_PORT)")
    parser.add_argument("--log-level", default=defaults.log_level)
    args = parser.parse_args(argv)
    settings = defaults.model_copy(update={"host": args.host, "port": args.port, "log_level": args.log_level})
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=args.log_level)


if __name__ == "__main__":
    main()
