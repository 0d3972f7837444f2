"""numpy body model: hand-checked kinematics, batch consistency, input validation (no anny needed)."""
import numpy as np
import pytest

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, interpolation_weights
from inference.errors import InputShapeError


@pytest.fixture(scope="module")
def body():
    return BodyModel.load()


def test_interpolation_weights_hat_functions():
    w = interpolation_weights(np.array([-1.0, 0.0, 0.25, 1.0, 2.0]), np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(w, [[1, 0, 0], [1, 0, 0], [0.5, 0.5, 0], [0, 0, 1], [0, 0, 1]])


def test_rest_pose_is_identity_transform(body):
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    J = body.num_bones
    W, T = body.pose(shape.rest_bone_poses, np.zeros((1, 2, J, 3), np.float32), np.zeros((1, 2, 3), np.float32))
    np.testing.assert_allclose(W[0, 0], shape.rest_bone_poses[0], atol=1e-6)
    np.testing.assert_allclose(T, np.broadcast_to(np.eye(4), T.shape), atol=1e-6)
    verts = body.skin(shape.rest_vertices, T)
    np.testing.assert_allclose(verts[0, 1], shape.rest_vertices[0], atol=1e-6)


def test_root_translation_and_rotation(body):
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    J = body.num_bones
    rot = np.zeros((1, 1, J, 3), np.float32)
    rot[0, 0, 0] = [0, 0, np.pi / 2]  # quarter turn about Z
    trans = np.array([[[0.1, 0.2, 0.3]]], np.float32)
    W, T = body.pose(shape.rest_bone_poses, rot, trans)
    h0 = shape.bone_heads[0, 0]
    np.testing.assert_allclose(W[0, 0, 0, :3, 3], h0 + trans[0, 0], atol=1e-6)
    # every head rotates about the root head by 90 degrees about Z, then translates
    rel = shape.bone_heads[0] - h0
    expected = np.stack([-rel[:, 1], rel[:, 0], rel[:, 2]], 1) + h0 + trans[0, 0]
    np.testing.assert_allclose(W[0, 0, :, :3, 3], expected, atol=1e-5)


def test_bone_rotation_moves_only_its_subtree(body):
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    J = body.num_bones
    j = body.bone_names.index("LeftForeArm")
    rot = np.zeros((1, 1, J, 3), np.float32)
    rot[0, 0, j] = [0.0, 0.0, 1.0]
    W, _ = body.pose(shape.rest_bone_poses, rot, np.zeros((1, 1, 3), np.float32))
    moved = np.linalg.norm(W[0, 0, :, :3, 3] - shape.bone_heads[0], axis=1) > 1e-6
    assert set(np.flatnonzero(moved)) == {body.bone_names.index(n) for n in ["LeftHand", "LThumb", "LeftFingerBase", "LeftHandFinger1"]}
    # the bone's own +Y axis (head -> tail) keeps its length and rotates 1 radian about local Z
    R_rest = shape.rest_bone_poses[0, j, :3, :3]
    R_posed = W[0, 0, j, :3, :3]
    cos = np.clip((np.trace(R_rest.T @ R_posed) - 1) / 2, -1, 1)
    assert abs(np.arccos(cos) - 1.0) < 1e-5


def test_batch_consistency(body):
    rng = np.random.default_rng(3)
    ph = rng.random((4, 6)).astype(np.float32)
    rot = (rng.normal(size=(4, 3, body.num_bones, 3)) * 0.3).astype(np.float32)
    trans = rng.normal(size=(4, 3, 3)).astype(np.float32)
    s4 = body.shape(ph)
    _, T4 = body.pose(s4.rest_bone_poses, rot, trans)
    v4 = body.skin(s4.rest_vertices, T4)
    s1 = body.shape(ph[2:3])
    _, T1 = body.pose(s1.rest_bone_poses, rot[2:3], trans[2:3])
    v1 = body.skin(s1.rest_vertices, T1)
    np.testing.assert_allclose(v4[2:3], v1, atol=1e-5)
    assert v4.dtype == np.float32 and v4.shape == (4, 3, body.num_vertices, 3)


def test_shape_changes_body_height(body):
    s = body.shape(np.array([[0.5, 0.8, 0.5, 0.5, 0.0, 0.5], [0.5, 0.8, 0.5, 0.5, 1.0, 0.5]], np.float32))
    height = s.rest_vertices[..., 2].max(1) - s.rest_vertices[..., 2].min(1)
    assert 1.2 < height[0] < height[1] < 2.5, height


def test_bad_shapes_raise(body):
    with pytest.raises(InputShapeError):
        body.shape(np.zeros((2, 5), np.float32))
    s = body.shape(NEUTRAL_PHENOTYPES[None])
    with pytest.raises(InputShapeError):
        body.pose(s.rest_bone_poses, np.zeros((1, 2, 30, 3), np.float32), np.zeros((1, 2, 3), np.float32))
