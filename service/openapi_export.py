"""Write the app's OpenAPI document to ``openapi.yaml`` (the contract; a test keeps them equal).

Run: ``python -m service.openapi_export``
"""
from __future__ import annotations

from pathlib import Path

import yaml

from service.app import create_app

OPENAPI_PATH = Path(__file__).resolve().parents[1] / "openapi.yaml"


def openapi_yaml() -> str:
    """The app's schema as YAML (keys in the app's order)."""
    return yaml.safe_dump(create_app().openapi(), sort_keys=False, allow_unicode=True, width=100)


def main() -> None:
    OPENAPI_PATH.write_text(openapi_yaml())


if __name__ == "__main__":
    main()
