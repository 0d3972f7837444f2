"""Motion descriptor gamma: layout, invariances, hand-computed velocities, batching."""
from __future__ import annotations

import numpy as np
import pytest

from inference import rotations as rot
from inference.errors import InputShapeError, InputValueError
from inference.motion.descriptor import (
    DESCRIPTOR_BONES,
    DESCRIPTOR_LAYOUT as L,
    DESCRIPTOR_SIZE,
    heading_rotation,
    motion_descriptor,
    rotation_6d,
)


def random_clip(T=40, B=1, seed=0):
    """A smooth random motion: rotations (B, T, 31, 3), translation (B, T, 3)."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 2, T)
    a, w, p = rng.normal(size=(3, B, 1, 31, 3))
    rotations = (0.4 * a * np.sin(3 * w * s[None, :, None, None] + p)).astype(np.float32)
    rotations[:, :, 0, 2] += (0.8 * s).astype(np.float32)  # turning
    translation = np.stack([np.sin(s), 1.3 * s, 0.05 * np.cos(5 * s)], -1).astype(np.float32)
    return rotations, np.broadcast_to(translation, (B, T, 3)).copy()


def test_layout_covers_the_vector():
    assert DESCRIPTOR_SIZE == 378 == 6 + 3 * 6 * len(DESCRIPTOR_BONES) + 12
    covered = np.zeros(DESCRIPTOR_SIZE, int)
    for s in L.values():
        covered[s] += 1
    assert np.all(covered == 1)
    rv, tr = random_clip()
    g = motion_descriptor(rv, tr, 30.0)
    assert g.shape == (1, 40, DESCRIPTOR_SIZE) and g.dtype == np.float32 and np.all(np.isfinite(g))


def test_invariant_to_rotation_about_z_and_translation():
    rv, tr = random_clip(T=50)
    Q = rot.axis_angle_to_matrix(np.array([0.0, 0.0, 2.1]))
    rv2 = rv.astype(np.float64).copy()
    rv2[:, :, 0] = rot.matrix_to_axis_angle(Q @ rot.axis_angle_to_matrix(rv2[:, :, 0]))
    tr2 = tr.astype(np.float64) @ Q.T + np.array([4.0, -7.0, 0.3])
    g1 = motion_descriptor(rv.astype(np.float64), tr.astype(np.float64), 30.0)
    g2 = motion_descriptor(rv2, tr2, 30.0)
    # float32 output; accelerations are O(100) (fps^2 scaled differences)
    np.testing.assert_allclose(g2, g1, atol=2e-3, rtol=1e-4)


def test_static_pose_has_zero_derivatives():
    rv, tr = random_clip(T=1)
    rv = np.repeat(rv, 12, axis=1)
    tr = np.repeat(tr, 12, axis=1)
    g = motion_descriptor(rv, tr, 30.0)
    moving = np.concatenate([g[..., s] for k, s in L.items() if k not in ("pose", "root_tilt")], -1)
    assert np.abs(moving).max() < 1e-5
    np.testing.assert_allclose(g[0, :, L["pose"]], np.broadcast_to(g[0, :1, L["pose"]], (12, 120)))
    # a single frame is valid too
    assert np.abs(motion_descriptor(rv[:, :1], tr[:, :1], 30.0)[..., L["pose_velocity"]]).max() == 0


def test_hand_computed_root_velocities_in_heading_frame():
    # The root turned by yaw(t) = 90 deg + 0.5 rad/s * t about Z (at t = 0 it faces +X: Rz(90) maps
    # the rest forward -Y to +X) while the body moves along world +X at 2 m/s.
    T, fps = 10, 20.0
    t = np.arange(T) / fps
    rv = np.zeros((1, T, 31, 3))
    yaw = np.pi / 2 + 0.5 * t
    rv[0, :, 0, 2] = yaw
    tr = np.zeros((1, T, 3))
    tr[0, :, 0] = 2.0 * t
    g = motion_descriptor(rv, tr, fps)[0]
    # Heading frame at t: Rz(yaw); world +X expressed in it: (cos yaw, -sin yaw, 0).
    expected_v = np.stack([2 * np.cos(yaw), -2 * np.sin(yaw), 0 * yaw], -1)
    np.testing.assert_allclose(g[:, L["root_linear_velocity"]], expected_v, atol=1e-5)
    np.testing.assert_allclose(g[:, L["root_angular_velocity"]], np.tile([0, 0, 0.5], (T, 1)), atol=1e-5)
    assert np.abs(g[:, L["root_angular_acceleration"]]).max() < 1e-4
    assert np.abs(g[:, L["root_linear_acceleration"]]).max() < 1e-4
    # upright root: tilt is the identity
    np.testing.assert_allclose(g[:, L["root_tilt"]], np.tile([1, 0, 0, 0, 1, 0], (T, 1)), atol=1e-6)


def test_pose_velocity_and_acceleration_are_per_second():
    T, fps = 8, 30.0
    rv = np.zeros((1, T, 31, 3))
    knee = 3  # LeftLeg
    rv[0, :, knee, 0] = 0.01 * np.arange(T) ** 2  # angle(t) = 0.01 k^2
    g = motion_descriptor(rv, np.zeros((1, T, 3)), fps)[0]
    k = DESCRIPTOR_BONES.index("LeftLeg")
    pose = g[:, L["pose"]].reshape(T, -1, 6)[:, k]
    expected = rotation_6d(rot.axis_angle_to_matrix(rv[0, :, knee]))
    np.testing.assert_allclose(pose, expected, atol=1e-6)
    vel = g[:, L["pose_velocity"]].reshape(T, -1, 6)[:, k]
    np.testing.assert_allclose(vel[1:], (expected[1:] - expected[:-1]) * fps, atol=1e-4)
    np.testing.assert_allclose(vel[0], vel[1])
    acc = g[:, L["pose_acceleration"]].reshape(T, -1, 6)[:, k]
    np.testing.assert_allclose(acc[2:], (vel[2:] - vel[1:-1]) * fps, atol=1e-2)
    np.testing.assert_allclose(acc[:2], 0.0, atol=1e-6)


def test_batch_consistency():
    rv, tr = random_clip(T=20, B=3, seed=4)
    g = motion_descriptor(rv, tr, 30.0)
    for b in range(3):
        np.testing.assert_allclose(g[b : b + 1], motion_descriptor(rv[b : b + 1], tr[b : b + 1], 30.0), atol=1e-6)


def test_heading_of_tilted_and_vertical_roots():
    # Pitched forward 80 deg about X and turned 30 deg: heading is the 30 deg turn.
    R = rot.axis_angle_to_matrix(np.array([0, 0, np.radians(30)])) @ rot.axis_angle_to_matrix(np.array([np.radians(80), 0, 0]))
    np.testing.assert_allclose(heading_rotation(R), rot.axis_angle_to_matrix(np.array([0, 0, np.radians(30)])), atol=1e-9)
    # Face straight down (forward -Y pitched to -Z): falls back to the root's up axis.
    R = rot.axis_angle_to_matrix(np.array([np.pi / 2, 0, 0]))
    H = heading_rotation(R)
    assert np.all(np.isfinite(H)) and np.allclose(H @ H.T, np.eye(3), atol=1e-9)


def test_bad_inputs():
    rv, tr = random_clip(T=5)
    with pytest.raises(InputShapeError):
        motion_descriptor(rv[:, :, :30], tr, 30.0)
    with pytest.raises(InputShapeError):
        motion_descriptor(rv, tr[:, :4], 30.0)
    with pytest.raises(InputValueError):
        motion_descriptor(rv, tr, 0.0)
    rv[0, 2, 3, 1] = np.nan
    with pytest.raises(InputValueError):
        motion_descriptor(rv, tr, 30.0)
