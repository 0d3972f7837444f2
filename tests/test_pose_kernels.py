"""The compiled forward kinematics (inference.pose_kernels, behind BodyModel.pose) against the
numpy form it replaced, and the arm lift's compiled bone rotation against its numpy form."""
import numpy as np
import pytest

from inference.body import BodyModel
from inference.motion.arm_kernels import rotate_bone
from inference.rotations import axis_angle_to_matrix, matrix_to_axis_angle


@pytest.fixture(scope="module")
def body():
    return BodyModel.load()


def _pose_numpy(body, rest_bone_poses, rotations, translation):
    """BodyModel.pose before it was compiled: K_c = [R_p^T R_c D_c | R_p^T (h_c - h_p)], W_c = W_p K_c
    one depth level at a time, T_c = W_c P_c^-1."""
    B, J = rest_bone_poses.shape[:2]
    T = rotations.shape[1]
    P = rest_bone_poses.astype(np.float64)[:, None]
    R, h = P[..., :3, :3], P[..., :3, 3]
    D = axis_angle_to_matrix(rotations.astype(np.float64))
    par = body.parents.copy()
    par[0] = 0
    Rp_t = np.swapaxes(R[..., par, :, :], -1, -2)
    K = np.zeros((B, T, J, 4, 4))
    K[..., :3, :3] = Rp_t @ R @ D
    K[..., :3, 3] = np.einsum("...ij,...j->...i", Rp_t, h - h[..., par, :])
    K[..., 3, 3] = 1.0
    W = np.zeros_like(K)
    W[..., 0, :3, :3] = R[..., 0, :, :] @ D[..., 0, :, :]
    W[..., 0, :3, 3] = h[..., 0, :] + translation
    W[..., 0, 3, 3] = 1.0
    for level in body.levels[1:]:
        W[..., level, :, :] = W[..., body.parents[level], :, :] @ K[..., level, :, :]
    TR = W[..., :3, :3] @ np.swapaxes(R, -1, -2)
    transforms = np.zeros_like(W)
    transforms[..., :3, :3] = TR
    transforms[..., :3, 3] = W[..., :3, 3] - np.einsum("...ij,...j->...i", TR, h)
    transforms[..., 3, 3] = 1.0
    return W.astype(np.float32), transforms.astype(np.float32)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_forward_kinematics_is_the_numpy_form(body, dtype):
    rng = np.random.default_rng(0)
    shape = body.shape(rng.uniform(0.0, 1.0, (2, 6)).astype(np.float32))
    rot = (rng.normal(size=(2, 9, body.num_bones, 3)) * 0.7).astype(dtype)
    trans = rng.normal(size=(2, 9, 3)).astype(dtype)
    rot[:, 0], trans[:, 0] = 0.0, 0.0  # the rest pose
    rest = shape.rest_bone_poses.astype(dtype)
    W, T = body.pose(rest, rot, trans)
    W_ref, T_ref = _pose_numpy(body, rest, rot, trans)
    assert W.dtype == T.dtype == np.float32
    np.testing.assert_allclose(W, W_ref, rtol=0, atol=1e-6)
    np.testing.assert_allclose(T, T_ref, rtol=0, atol=1e-6)
    # the rest pose's transforms are the identity; every bone pose is rigid
    np.testing.assert_allclose(T[:, 0], np.broadcast_to(np.eye(4), T[:, 0].shape), atol=1e-5)
    Rw = W[..., :3, :3].astype(np.float64)
    np.testing.assert_allclose(Rw @ np.swapaxes(Rw, -1, -2), np.broadcast_to(np.eye(3), Rw.shape), atol=1e-5)


def test_the_arms_new_rotation_is_the_numpy_form(body):
    rng = np.random.default_rng(1)
    shape = body.shape(rng.uniform(0.0, 1.0, (1, 6)).astype(np.float32))
    n = 40
    rot = (rng.normal(size=(n, body.num_bones, 3)) * 0.5).astype(np.float32)
    W, _ = body.pose(shape.rest_bone_poses, rot[None], np.zeros((1, n, 3), np.float32))
    bone = body.bone_names.index("LeftArm")
    parent = body.parents[bone]
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    theta = rng.uniform(0.0, 0.25, n)
    R = shape.rest_bone_poses[0, :, :3, :3].astype(np.float64)
    A = W[0, :, parent, :3, :3].astype(np.float64) @ (R[parent].T @ R[bone])
    Q = axis_angle_to_matrix(axes * theta[:, None])
    D = axis_angle_to_matrix(rot[:, bone].astype(np.float64))
    ref = matrix_to_axis_angle(np.swapaxes(A, -1, -2) @ Q @ A @ D).astype(np.float32)
    out = np.empty((n, 3), np.float32)
    rotate_bone(np.ascontiguousarray(W[0, :, parent, :3, :3]), R[parent].T @ R[bone], axes, theta, rot[:, bone], out)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-6)
    assert np.abs(out - rot[:, bone]).max() > 0.01  # it did rotate
