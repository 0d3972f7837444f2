"""``python -m service.healthcheck [URL]``: the container's health check (exit 0 when /readyz is
200). Standard library only, so it needs no curl in the image."""
from __future__ import annotations

import os
import sys
import urllib.request


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    url = argv[0] if argv else f"http://127.0.0.1:{os.environ.get('TRYON_PORT', '8000')}/readyz"
    try:
        with urllib.request.urlopen(url, timeout=3) as r:  # noqa: S310 - a local URL from the operator
            return 0 if r.status == 200 else 1
    except Exception:  # noqa: BLE001 - any failure is "unhealthy"
        return 1


if __name__ == "__main__":
    sys.exit(main())
