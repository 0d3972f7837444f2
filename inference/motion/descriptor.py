"""Motion descriptor gamma, thesis eq. 6.17 adapted to the cmu_mb body.

Eq. 6.17: gamma = {theta_bar, d theta_bar/dt, d2 theta_bar/dt2, dH/dt, d2H/dt2, dK/dt, d2K/dt2}
with theta_bar a pose descriptor, H the global translation and K the global rotation. Ours:

- theta_bar: the 6D rotation representation (Zhou et al. 2019: the first two columns of the
  rotation matrix, continuous, unlike axis-angle or Euler angles) of the local rotation of the
  DESCRIPTOR_BONES (the 30 non-root bones minus the hip-joint bones, which mocap never moves
  relative to the pelvis, the toes and the thumb/finger bones, which barely move cloth), plus
  the root's tilt: its rotation in the heading frame (added: the direction of gravity in the
  body's frame matters for cloth; the thesis' theta includes the global orientation).
- the heading frame Hd(t): the rotation about Z that takes the body's rest forward (-Y) to the
  horizontal part of the root's forward R_0(t) (-Y) (to the root's up axis R_0(t) Z if the
  forward is vertical). The root's linear (dH/dt, from ``translation``) and angular (dK/dt)
  velocities and accelerations are computed in the world and expressed in Hd(t), so gamma
  does not change when the whole clip is rotated about Z or moved.
- derivatives: backward finite differences per second (x(t) - x(t-1)) * fps, angular velocity
  log(R_0(t) R_0(t-1)^T) * fps; the clip is extended backwards at constant velocity, so
  v(0) = v(1) and a(0) = a(1) = 0. A single frame has zero derivatives.

Layout of the last axis (DESCRIPTOR_SIZE = 378), see DESCRIPTOR_LAYOUT:
  [  0,   6) root tilt, 6D                                  (unitless)
  [  6, 126) pose: 20 bones x 6D, DESCRIPTOR_BONES order     (unitless)
  [126, 246) pose velocity                                   (1/s)
  [246, 366) pose acceleration                               (1/s^2)
  [366, 369) root linear velocity, heading frame (x, y, z)   (m/s)
  [369, 372) root linear acceleration, heading frame         (m/s^2)
  [372, 375) root angular velocity, heading frame            (rad/s)
  [375, 378) root angular acceleration, heading frame        (rad/s^2)
"""
from __future__ import annotations

import numpy as np

from inference import rotations as rot
from inference.errors import InputShapeError, InputValueError
from inference.motion.names import CMU_MB_BONES

DESCRIPTOR_BONES: tuple[str, ...] = (
    "LeftUpLeg", "LeftLeg", "LeftFoot", "LowerBack", "Spine", "Spine1",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "Neck", "Neck1", "Head",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand", "RightUpLeg", "RightLeg", "RightFoot",
)  # fmt: skip
DESCRIPTOR_BONE_INDEX = np.array([CMU_MB_BONES.index(n) for n in DESCRIPTOR_BONES], dtype=np.int64)
_NP = 6 * len(DESCRIPTOR_BONES)
DESCRIPTOR_LAYOUT: dict[str, slice] = {
    "root_tilt": slice(0, 6),
    "pose": slice(6, 6 + _NP),
    "pose_velocity": slice(6 + _NP, 6 + 2 * _NP),
    "pose_acceleration": slice(6 + 2 * _NP, 6 + 3 * _NP),
    "root_linear_velocity": slice(6 + 3 * _NP, 9 + 3 * _NP),
    "root_linear_acceleration": slice(9 + 3 * _NP, 12 + 3 * _NP),
    "root_angular_velocity": slice(12 + 3 * _NP, 15 + 3 * _NP),
    "root_angular_acceleration": slice(15 + 3 * _NP, 18 + 3 * _NP),
}
DESCRIPTOR_SIZE = 18 + 3 * _NP  # 378
FORWARD = np.array([0.0, -1.0, 0.0])


def rotation_6d(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): the first two columns, (R00, R10, R20, R01, R11, R21)."""
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def heading_rotation(root_R: np.ndarray) -> np.ndarray:
    """Heading frame Hd: rotation about Z aligning -Y with the root's horizontal forward.

    root_R  : (..., 3, 3) root world rotations
    returns : (..., 3, 3)
    """
    f = root_R @ FORWARD  # (..., 3)
    u = root_R[..., :, 2]  # the root's up axis, for a vertical forward
    use_up = np.hypot(f[..., 0], f[..., 1]) < 1e-3
    f = np.where(use_up[..., None], u, f)
    # angle of the horizontal forward relative to -Y (whose angle is -pi/2)
    yaw = np.arctan2(f[..., 1], f[..., 0]) + np.pi / 2
    c, s = np.cos(yaw), np.sin(yaw)
    o, z = np.ones_like(yaw), np.zeros_like(yaw)
    return np.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(yaw.shape + (3, 3))


def _diff(x: np.ndarray, fps: float) -> np.ndarray:
    """Backward difference per second along axis 1, with d[0] = d[1] (constant-velocity start)."""
    d = np.zeros_like(x)
    if x.shape[1] > 1:
        d[:, 1:] = (x[:, 1:] - x[:, :-1]) * fps
        d[:, 0] = d[:, 1]
    return d


def motion_descriptor(rotations: np.ndarray, translation: np.ndarray, fps: float) -> np.ndarray:
    """Per-frame motion descriptor gamma (thesis eq. 6.17 adapted; layout in the module doc).

    rotations   : (B, T, 31, 3) axis-angle radians, cmu_mb pose contract (inference/body.py)
    translation : (B, T, 3) metres, root displacement, world Z-up
    fps         : frames per second (> 0)
    returns     : (B, T, DESCRIPTOR_SIZE) float32
    """
    rotations = np.asarray(rotations)
    translation = np.asarray(translation)
    if rotations.ndim != 4 or rotations.shape[2:] != (len(CMU_MB_BONES), 3):
        raise InputShapeError("rotations", f"(B, T, {len(CMU_MB_BONES)}, 3)", rotations.shape)
    B, T = rotations.shape[:2]
    if translation.shape != (B, T, 3):
        raise InputShapeError("translation", f"({B}, {T}, 3)", translation.shape)
    if not (np.isfinite(fps) and fps > 0):
        raise InputValueError("fps", f"must be a positive number of frames per second, got {fps}")
    if not (np.all(np.isfinite(rotations)) and np.all(np.isfinite(translation))):
        raise InputValueError("rotations", "rotations and translation must be finite")
    fps = float(fps)

    R_root = rot.axis_angle_to_matrix(rotations[:, :, 0].astype(np.float64))  # (B, T, 3, 3)
    Hd = heading_rotation(R_root)
    HdT = np.swapaxes(Hd, -1, -2)
    tilt = rotation_6d(HdT @ R_root)  # root rotation in the heading frame

    pose = rotation_6d(rot.axis_angle_to_matrix(rotations[:, :, DESCRIPTOR_BONE_INDEX].astype(np.float64)))
    pose = pose.reshape(B, T, -1)  # (B, T, 120)
    pose_vel = _diff(pose, fps)
    pose_acc = _diff(pose_vel, fps)

    lin_vel = _diff(translation.astype(np.float64), fps)  # world, m/s
    lin_acc = _diff(lin_vel, fps)
    ang_vel = np.zeros((B, T, 3))
    if T > 1:
        step = R_root[:, 1:] @ np.swapaxes(R_root[:, :-1], -1, -2)  # R(t) R(t-1)^T, world
        ang_vel[:, 1:] = rot.matrix_to_axis_angle(step) * fps
        ang_vel[:, 0] = ang_vel[:, 1]
    ang_acc = _diff(ang_vel, fps)

    def local(v: np.ndarray) -> np.ndarray:  # world vector -> heading frame, Hd^T v
        return np.einsum("btij,btj->bti", HdT, v)

    gamma = np.concatenate(
        [tilt, pose, pose_vel, pose_acc, local(lin_vel), local(lin_acc), local(ang_vel), local(ang_acc)], axis=-1
    )
    return gamma.astype(np.float32)
