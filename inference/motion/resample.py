"""Resample a pose sequence to another frame rate: slerp for rotations, lerp for translation."""
from __future__ import annotations

import math

import numpy as np

from inference import rotations as rot

DEFAULT_FPS = 30.0


def resampled_frame_count(num_frames: int, fps_in: float, fps_out: float) -> int:
    """Frames a clip of ``num_frames`` at ``fps_in`` has at ``fps_out`` (``resample_times``):
    floor((num_frames - 1) / fps_in * fps_out + 1e-6) + 1, computed before any array is made, so
    that a caller can refuse an oversized request first (saturates at 2**62 for absurd rates)."""
    if not (fps_in > 0 and fps_out > 0 and math.isfinite(fps_in) and math.isfinite(fps_out)):
        raise ValueError(f"frame rates must be positive, got {fps_in} -> {fps_out}")
    n = (max(int(num_frames), 1) - 1) / fps_in * fps_out + 1e-6
    return int(math.floor(n)) + 1 if math.isfinite(n) and n < 2.0**62 else 2**62


def resample_times(num_frames: int, fps_in: float, fps_out: float) -> np.ndarray:
    """Output sample times (seconds) covering the input clip's duration.

    The input spans (num_frames - 1) / fps_in seconds; the output has
    floor(duration * fps_out + 1e-6) + 1 frames at k / fps_out, so the duration is kept to
    within one output frame and both clips start at t = 0.
    returns : (T_out,) float64 seconds
    """
    if not (fps_in > 0 and fps_out > 0 and math.isfinite(fps_in) and math.isfinite(fps_out)):
        raise ValueError(f"frame rates must be positive, got {fps_in} -> {fps_out}")
    return np.arange(resampled_frame_count(num_frames, fps_in, fps_out)) / fps_out


def resample_rotations(rotvecs: np.ndarray, times_in_frames: np.ndarray) -> np.ndarray:
    """Slerp per-bone rotations at fractional frame indices.

    rotvecs         : (..., T, J, 3) axis-angle radians, frames on axis -3
    times_in_frames : (T_out,) fractional input frame indices in [0, T - 1]
    returns         : (..., T_out, J, 3) float32
    """
    rotvecs = np.asarray(rotvecs, dtype=np.float32)
    T = rotvecs.shape[-3]
    i0, i1, w = _brackets(times_in_frames, T)
    q = rot.axis_angle_to_quaternion(rotvecs)
    q0, q1 = q[..., i0, :, :], q[..., i1, :, :]
    w = np.broadcast_to(w[:, None], q0.shape[-3:-1]).astype(np.float32)
    return rot.quaternion_to_axis_angle(rot.quaternion_slerp(q0, q1, w)).astype(np.float32)


def resample_translation(translation: np.ndarray, times_in_frames: np.ndarray) -> np.ndarray:
    """Linear interpolation at fractional frame indices.

    translation : (..., T, 3) metres
    returns     : (..., T_out, 3) float32
    """
    translation = np.asarray(translation, dtype=np.float32)
    i0, i1, w = _brackets(times_in_frames, translation.shape[-2])
    w = w[:, None].astype(np.float32)
    return ((1 - w) * translation[..., i0, :] + w * translation[..., i1, :]).astype(np.float32)


def resample_motion(
    rotations: np.ndarray, translation: np.ndarray, fps_in: float, fps_out: float = DEFAULT_FPS
) -> tuple[np.ndarray, np.ndarray]:
    """Resample a pose sequence to ``fps_out``, keeping its duration (see resample_times).

    rotations   : (..., T, J, 3) axis-angle radians (local, per bone)
    translation : (..., T, 3) metres
    returns     : rotations (..., T_out, J, 3) float32, translation (..., T_out, 3) float32
    """
    T = np.shape(rotations)[-3]
    if np.shape(translation)[-2] != T:
        raise ValueError(f"rotations have {T} frames, translation {np.shape(translation)[-2]}")
    frames = resample_times(T, fps_in, fps_out) * fps_in
    return resample_rotations(rotations, frames), resample_translation(translation, frames)


def _brackets(frames: np.ndarray, T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = np.clip(np.asarray(frames, dtype=np.float64), 0, T - 1)
    i0 = np.minimum(np.floor(f).astype(np.int64), T - 1)
    i1 = np.minimum(i0 + 1, T - 1)
    return i0, i1, f - i0
