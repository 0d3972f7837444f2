"""Shared fixtures: one loaded runtime and app per test session (assets load once)."""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
# anny's and warp's caches under build/ (ignored by git), not ~/.cache, also for the README's
# plain `pytest` command: set before any test module imports anny or warp.
os.environ.setdefault("ANNY_CACHE_DIR", str(REPO_ROOT / "build" / "anny_cache"))
os.environ.setdefault("WARP_CACHE_PATH", str(REPO_ROOT / "build" / "warp_cache"))
VALIDATOR = REPO_ROOT / "tools" / "validate_gltf.mjs"


@pytest.fixture(scope="session")
def settings():
    from service.config import Settings

    return Settings()


@pytest.fixture(scope="session")
def runtime(settings):
    from service.runtime import Runtime

    return Runtime.load(settings)


@pytest.fixture(scope="session")
def client(settings, runtime):
    from fastapi.testclient import TestClient

    from service.app import create_app

    with TestClient(create_app(settings, runtime), raise_server_exceptions=False) as c:
        yield c


def validate_glb(path: Path) -> dict:
    """Run the Khronos glTF validator (npm gltf-validator) on a file; skip if it is not installed."""
    import json

    if shutil.which("node") is None or not (REPO_ROOT / "node_modules" / "gltf-validator").exists():
        pytest.skip("gltf-validator not installed: run `npm ci` at the repository root")
    proc = subprocess.run(["node", str(VALIDATOR), str(path)], capture_output=True, text=True, timeout=120)
    return json.loads(proc.stdout)
