"""Rebuild ``assets/manifest.json``: every shipped asset file with its sha256, size and the
command that rebuilt it.

Run: ``python -m training.manifest`` (after any asset build).
"""
from __future__ import annotations

import logging
import json
import subprocess
from pathlib import Path

from inference.asset_digest import file_sha256
from training.assets.anny_model import REPO_ROOT

ASSETS = REPO_ROOT / "assets"
# First matching prefix wins: asset path (relative to assets/) -> build command.
BUILD_COMMANDS = [
    ("body/diffused.npz", "python -m training.assets.build_diffused_body"),
    ("body/", "python -m training.assets.build_body"),
    ("garments/", "python -m training.assets.build_garments"),
    ("motions/", "python -m training.assets.build_motions"),
    ("models/defaults.json", "hand-written: each garment's default method, from docs/evaluation.md (inference/defaults.py)"),
    ("models/", "see the model's own entry (training config in ONNX metadata)"),
]


sha256 = file_sha256  # the runtime's own hash of a file (versions come from the same bytes)


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def build_manifest(assets: Path = ASSETS) -> dict:
    entries = []
    for path in sorted(p for p in assets.rglob("*") if p.is_file() and p.name != "manifest.json"):
        rel = path.relative_to(assets).as_posix()
        command = next((c for prefix, c in BUILD_COMMANDS if rel.startswith(prefix)), "hand-written")
        entries.append({"path": rel, "sha256": sha256(path), "bytes": path.stat().st_size, "built_by": command})
    return {"format": 1, "git_commit_at_build": git_commit(), "assets": entries}


def main() -> None:
    manifest = build_manifest()
    (ASSETS / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    logging.basicConfig(level=logging.INFO)
    logging.getLogger(__name__).info("%d assets", len(manifest["assets"]))


if __name__ == "__main__":
    main()
