"""Construct the anny models the project is built on (training side only).

anny writes a ~830 MB cache on first use; it goes under ``ANNY_CACHE_DIR`` (default
``build/anny_cache`` inside the repository, git-ignored), never the home directory.
"""
from __future__ import annotations

import functools
import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CACHE_DIR = REPO_ROOT / "build" / "anny_cache"

RIG = "cmu_mb"
POSE_PARAMETERIZATION = "local-bone-world"  # the service's pose contract, see inference/body.py


def _ensure_cache_dir() -> None:
    os.environ.setdefault("ANNY_CACHE_DIR", str(DEFAULT_CACHE_DIR))
    # warp (pulled in by anny) writes compiled kernels; keep them out of the home directory too.
    os.environ.setdefault("WARP_CACHE_PATH", str(REPO_ROOT / "build" / "warp_cache"))
    Path(os.environ["ANNY_CACHE_DIR"]).mkdir(parents=True, exist_ok=True)


@functools.lru_cache(maxsize=4)
def load_anny(topology: str = "anny"):
    """The anny model with rig cmu_mb, float64, plain LBS (no warp), our pose parameterization.

    topology: "anny" (13,718 skin vertices) or "anny-full" (19,158, MakeHuman hm08 order).
    """
    _ensure_cache_dir()
    import anny  # noqa: PLC0415  (heavy, training-only import)

    return anny.Anny(
        rig=RIG,
        topology=topology,
        pose_parameterization=POSE_PARAMETERIZATION,
        skinning_method="lbs",
    )
