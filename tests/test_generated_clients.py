"""Generated clients of the contract: tools/check_clients.sh (openapi-typescript 7 + tsc --strict,
openapi-python-client in a throwaway venv) keeps the binary responses and accepts the README
request with no edits to the generated code. It downloads the generators (npm registry, PyPI), so
it runs only with TRYON_CHECK_CLIENTS=1."""
from __future__ import annotations

import os
import shutil
import subprocess

import pytest

from tests.conftest import REPO_ROOT

SCRIPT = REPO_ROOT / "tools" / "check_clients.sh"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(os.environ.get("TRYON_CHECK_CLIENTS") != "1",
                       reason="downloads openapi-typescript, typescript and openapi-python-client: set TRYON_CHECK_CLIENTS=1"),
    pytest.mark.skipif(shutil.which("npx") is None or shutil.which("bash") is None, reason="needs bash and npx (Node 20)"),
    pytest.mark.timeout(600),
]


def test_generated_clients_keep_the_binary_responses_and_accept_the_readme_request(tmp_path):
    proc = subprocess.run(["bash", str(SCRIPT)], cwd=REPO_ROOT, capture_output=True, text=True, timeout=540,
                          env={**os.environ, "TMPDIR": str(tmp_path)})
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-6000:]
    for line in ("tsc --noEmit --strict client.ts: OK", "DrapeRequest.from_dict(readme).to_dict() == readme",
                 "drape.sync(README request): File with the", "job result.sync: File with the", "python client: OK",
                 "OK: both generated clients keep the binary responses"):
        assert line in out, out[-6000:]
