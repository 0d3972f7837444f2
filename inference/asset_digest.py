"""Content versions of the shipped assets: what a drape's output depends on, by SHA-256.

A drape's result is a function of the request, the code and the asset files it reads (body
model, garment data, ONNX models, motion clips). Cache keys and ETags use ``AssetDigest.combined``,
the SHA-256 over every such file's path and SHA-256, so that retraining a model or rebuilding a
garment changes every affected ETag without anyone bumping a version string. Files a drape never
reads are left out: ``manifest.json`` (this list itself), ``models/defaults.json`` (the cache key
holds the resolved default methods instead, so rewording a reason keeps the key), the template
``.glb`` files and READMEs.
"""
from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
NOT_READ_BY_A_DRAPE = ("manifest.json", "models/defaults.json")
NOT_READ_SUFFIXES = (".glb", ".md")


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class AssetDigest:
    """``files``: path relative to the assets directory -> SHA-256 (hex) of its bytes."""

    files: dict[str, str]

    @classmethod
    def of(cls, assets_dir: Path) -> "AssetDigest":
        """Hash the files a drape reads (~0.3 s for the shipped ~130 MB), and warn where the
        manifest's recorded hash differs (a file changed without ``python -m training.manifest``)."""
        assets_dir = Path(assets_dir)
        files = {}
        for path in sorted(p for p in assets_dir.rglob("*") if p.is_file()):
            rel = path.relative_to(assets_dir).as_posix()
            if rel in NOT_READ_BY_A_DRAPE or rel.endswith(NOT_READ_SUFFIXES):
                continue
            files[rel] = file_sha256(path)
        digest = cls(files)
        stale = digest.differs_from_manifest(assets_dir / MANIFEST)
        if stale:
            log.warning("assets/manifest.json is stale for %d file(s) (first: %s); versions use the files' own hashes", len(stale), stale[0])
        return digest

    @property
    def combined(self) -> str:
        """SHA-256 over the sorted ``path sha256`` lines: one version for all of them."""
        lines = "".join(f"{p} {h}\n" for p, h in sorted(self.files.items()))
        return hashlib.sha256(lines.encode()).hexdigest()

    def short(self, rel: str) -> str:
        """The first 16 hex digits of one file's hash ('absent' if the file is not shipped)."""
        return self.files.get(rel, "absent")[:16]

    def differs_from_manifest(self, manifest_path: Path) -> list[str]:
        """Paths whose manifest entry is missing or records another hash."""
        try:
            recorded = {e["path"]: e["sha256"] for e in json.loads(manifest_path.read_text())["assets"]}
        except (OSError, ValueError, KeyError, TypeError):
            return sorted(self.files)
        return [p for p, h in sorted(self.files.items()) if recorded.get(p) != h]
