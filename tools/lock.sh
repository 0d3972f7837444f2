#!/usr/bin/env bash
# Regenerate the runtime lock (requirements/runtime.lock: every runtime dependency pinned with its
# sha256 hashes, what the container image installs) and the same pins without hashes
# (requirements/runtime-constraints.txt: what the README's install and test commands use as pip
# constraints, so that CI tests the versions the image ships). Needs uv (pip install uv).
set -euo pipefail
cd "$(dirname "$0")/.."
common=(pyproject.toml --extra compress --python-version 3.11 --python-platform x86_64-manylinux_2_28
        --no-header --annotation-style line)
uv pip compile "${common[@]}" --generate-hashes -o requirements/runtime.lock
uv pip compile "${common[@]}" -o requirements/runtime-constraints.txt
