"""The tuned LBS kernel (``inference.body.linear_blend_skinning``: blocks of frames, coordinate
major) against its readable reference, over frame counts that fill one block, several and a
partial last one, with a rest shape shared by the frames or one per frame; points with their
normals; and the training's torch LBS against the numpy one."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import inference.body as body_module
from inference.body import linear_blend_skinning, linear_blend_skinning_reference, skin_points_and_normals


def _case(B: int, T: int, V: int, J: int, per_frame: bool, seed: int = 0):
    rng = np.random.default_rng(seed)
    w = rng.random((V, J)) ** 4
    w /= w.sum(1, keepdims=True)
    transforms = np.zeros((B, T, J, 4, 4), np.float32)
    transforms[..., :3, :3] = Rotation.random(B * T * J, random_state=seed).as_matrix().reshape(B, T, J, 3, 3)
    transforms[..., :3, 3] = rng.normal(size=(B, T, J, 3))
    transforms[..., 3, 3] = 1.0
    rest = rng.normal(size=(B, T, V, 3) if per_frame else (B, V, 3)).astype(np.float32)
    return rest, w.astype(np.float32), transforms


@pytest.mark.parametrize("frames", [1, 3, 17])
@pytest.mark.parametrize("per_frame", [False, True])
@pytest.mark.parametrize("block", [64_000, 4 * 50])  # one block for all frames; blocks of 4 frames (17 = 4 x 4 + 1)
def test_kernel_equals_the_reference(monkeypatch, frames, per_frame, block):
    monkeypatch.setattr(body_module, "_LBS_BLOCK", block)
    rest, w, transforms = _case(2, frames, 50, 7, per_frame)
    got = linear_blend_skinning(rest, w, transforms)
    assert got.shape == (2, frames, 50, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, linear_blend_skinning_reference(rest, w, transforms), atol=2e-5, rtol=0)


def test_the_reference_is_lbs_of_one_vertex_by_hand():
    rest = np.array([[[1.0, 0.0, 0.0]]], np.float32)
    w = np.array([[0.25, 0.75]], np.float32)
    transforms = np.tile(np.eye(4, dtype=np.float32), (1, 1, 2, 1, 1))
    transforms[0, 0, 0, :3, 3] = [0.0, 0.0, 4.0]  # bone 0 lifts by 4
    transforms[0, 0, 1, :3, :3] = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()  # bone 1 turns x into y
    expected = 0.25 * np.array([1.0, 0.0, 4.0]) + 0.75 * np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(linear_blend_skinning_reference(rest, w, transforms)[0, 0, 0], expected, atol=1e-6)


def test_training_torch_lbs_equals_numpy():
    torch = pytest.importorskip("torch")
    from training.train_wrinkle import skin_torch

    rest, w, transforms = _case(1, 5, 40, 6, per_frame=True, seed=3)
    got = skin_torch(torch.as_tensor(rest[0]), torch.as_tensor(w), torch.as_tensor(transforms[0])).numpy()
    np.testing.assert_allclose(got, linear_blend_skinning(rest, w, transforms)[0], atol=2e-5, rtol=0)


def test_normals_turn_with_the_bones_and_stay_unit():
    """One bone: the normals are the rest normals rotated (the translation does not move them),
    the points are transformed; blended bones: unit normals between the two rotations."""
    rest, w, transforms = _case(2, 3, 30, 4, per_frame=False, seed=5)
    normals = rest / np.linalg.norm(rest, axis=-1, keepdims=True)
    one = np.zeros_like(w)
    one[:, 2] = 1.0
    p, n = skin_points_and_normals(rest, normals, one, transforms)
    R, t = transforms[:, :, 2, :3, :3], transforms[:, :, 2, :3, 3]
    np.testing.assert_allclose(n, np.einsum("btik,bvk->btvi", R, normals), atol=1e-5)
    np.testing.assert_allclose(p, np.einsum("btik,bvk->btvi", R, rest) + t[:, :, None], atol=1e-5)
    p, n = skin_points_and_normals(rest, normals, w, transforms)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(p, linear_blend_skinning(rest, w, transforms), atol=0)


def test_training_torch_points_and_normals_equal_numpy():
    torch = pytest.importorskip("torch")
    from training.train_wrinkle import skin_points_and_normals_torch

    rest, w, transforms = _case(1, 4, 40, 6, per_frame=False, seed=7)
    normals = rest / np.linalg.norm(rest, axis=-1, keepdims=True)
    want_p, want_n = skin_points_and_normals(rest, normals, w, transforms)
    T = transforms.shape[1]
    got_p, got_n = skin_points_and_normals_torch(torch.as_tensor(rest).expand(T, -1, -1), torch.as_tensor(normals).expand(T, -1, -1),
                                                 torch.as_tensor(w), torch.as_tensor(transforms[0]))
    np.testing.assert_allclose(got_p.numpy(), want_p[0], atol=2e-5, rtol=0)
    np.testing.assert_allclose(got_n.numpy(), want_n[0], atol=2e-5, rtol=0)
