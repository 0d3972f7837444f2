"""Bundled motion clips (``assets/motions``): registry, loader, and adaptation to a body.

Each clip is ``assets/motions/<id>.npz`` (built by ``python -m training.assets.build_motions``):
  rotations    (T, 31, 3) float32, axis-angle radians, cmu_mb pose contract (inference/body.py)
  translation  (T, 3) float32, metres, root displacement; grounded: the feet touch z = 0
  fps          () float32
  leg_length_m () float32, leg length (retarget.leg_length) of the body it was retargeted onto
  phenotypes   (6,) float32, that body (the neutral one)
and ``assets/motions/index.json`` lists the clips (id, title, frames, fps, duration_s, source,
licence, test_only, description, ground_window_s, file).

A clip is stored for the neutral body. :func:`adapt_clip` moves it onto other bodies: the
rotations are kept (they are relative to each body's own rest frames), the root translation is
scaled by the ratio of leg lengths, and the feet are put back on z = 0 (retarget.floor_height).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inference.errors import UnknownAssetError
from inference.motion.retarget import floor_height, foot_heights, target_leg_length

DEFAULT_ASSETS_DIR = Path(__file__).resolve().parents[2] / "assets"
INDEX_FILE = "index.json"


@dataclass(frozen=True)
class Clip:
    """A bundled clip on the neutral body (arrays as in the module docstring)."""

    id: str
    rotations: np.ndarray
    translation: np.ndarray
    fps: float
    leg_length_m: float
    phenotypes: np.ndarray
    ground_window_s: float | None = 0.5
    meta: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def duration_s(self) -> float:
        return (self.num_frames - 1) / self.fps


def _motions_dir(assets_dir: str | Path | None) -> Path:
    return (Path(assets_dir) if assets_dir is not None else DEFAULT_ASSETS_DIR) / "motions"


def read_index(assets_dir: str | Path | None = None, *, include_test_only: bool = True) -> list[dict]:
    """The clip entries of ``assets/motions/index.json`` (list of dicts, in file order)."""
    with open(_motions_dir(assets_dir) / INDEX_FILE, encoding="utf-8") as f:
        entries = json.load(f)["clips"]
    return [e for e in entries if include_test_only or not e.get("test_only", False)]


def load_clip(clip_id: str, assets_dir: str | Path | None = None) -> Clip:
    """Load a bundled clip by id. Raises UnknownAssetError for an id the index does not list."""
    entries = {e["id"]: e for e in read_index(assets_dir)}
    entry = entries.get(clip_id)
    if entry is None:  # never build a path from an unknown id
        raise UnknownAssetError("motion.clip", f"unknown motion clip {clip_id!r}; known: {sorted(entries)}")
    with np.load(_motions_dir(assets_dir) / entry["file"], allow_pickle=False) as f:
        window = entry.get("ground_window_s")
        return Clip(
            id=clip_id,
            rotations=f["rotations"].astype(np.float32),
            translation=f["translation"].astype(np.float32),
            fps=float(f["fps"]),
            leg_length_m=float(f["leg_length_m"]),
            phenotypes=f["phenotypes"].astype(np.float32),
            ground_window_s=None if window is None else float(window),
            meta=entry,
        )


def scale_translation(translation: np.ndarray, leg_length_from_m: float, leg_lengths_to_m: np.ndarray) -> np.ndarray:
    """Scale a root translation to bodies with other leg lengths.

    translation      : (T, 3) metres, for a body with leg length ``leg_length_from_m``
    leg_lengths_to_m : (B,) metres
    returns          : (B, T, 3) float32, translation * (to / from) per body
    """
    ratio = np.asarray(leg_lengths_to_m, np.float32) / np.float32(leg_length_from_m)
    return (ratio[:, None, None] * np.asarray(translation, np.float32)[None]).astype(np.float32)


def adapt_clip(clip: Clip, body, shape) -> tuple[np.ndarray, np.ndarray]:
    """A clip for each body of ``shape``: same rotations, scaled translation, feet on z = 0.

    The vertical is corrected by the change of floor (retarget.floor_height) between the
    clip's own body and each new body, so the stored clip's contacts are kept as they are
    and the clip's own body gets the stored clip back unchanged.
    clip  : Clip ; body : BodyModel ; shape : BodyShape with B bodies
    returns : rotations (B, T, 31, 3) float32, translation (B, T, 3) float32
    """
    B = shape.rest_bone_poses.shape[0]
    legs = np.array([target_leg_length(shape, b) for b in range(B)])
    translation = scale_translation(clip.translation, clip.leg_length_m, legs)
    rotations = np.broadcast_to(clip.rotations, (B,) + clip.rotations.shape).astype(np.float32)
    window = clip.ground_window_s
    if window is not None and not math.isfinite(window):
        window = None
    own = body.shape(clip.phenotypes[None])
    floor_own = floor_height(foot_heights(body, own, clip.rotations[None], clip.translation[None]), clip.fps, window)
    floor_new = floor_height(foot_heights(body, shape, rotations, translation), clip.fps, window)
    translation[..., 2] -= (floor_new - floor_own).astype(np.float32)
    return rotations, translation


class ClipLibrary:
    """The bundled clips of one assets directory, index read once, clips loaded on demand."""

    SUMMARY_KEYS = ("id", "title", "frames", "fps", "duration_s", "test_only", "description")

    def __init__(self, assets_dir: str | Path | None = None):
        self.assets_dir = assets_dir
        self._entries = {e["id"]: e for e in read_index(assets_dir)}
        self._cache: dict[str, Clip] = {}

    def ids(self, include_test_only: bool = True) -> list[str]:
        return [i for i, e in self._entries.items() if include_test_only or not e.get("test_only", False)]

    def summary(self, clip_id: str) -> dict:
        """The index entry's public fields (id, title, frames, fps, duration_s, test_only, description)."""
        entry = self._entries.get(clip_id)
        if entry is None:
            raise UnknownAssetError("motion.clip", f"unknown motion clip {clip_id!r}; known: {sorted(self._entries)}")
        return {k: entry[k] for k in self.SUMMARY_KEYS}

    def load(self, clip_id: str) -> Clip:
        if clip_id not in self._cache:
            self._cache[clip_id] = load_clip(clip_id, self.assets_dir)
        return self._cache[clip_id]
