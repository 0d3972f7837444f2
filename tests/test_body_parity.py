"""Parity of the numpy body model (inference/body.py) with anny's own forward pass."""
import numpy as np
import pytest

from inference.body import NEUTRAL_PHENOTYPES, BodyModel

torch = pytest.importorskip("torch")
pytest.importorskip("anny")
pytestmark = pytest.mark.anny

from training.assets.anny_model import load_anny  # noqa: E402


@pytest.fixture(scope="module")
def body():
    return BodyModel.load()


def _anny_forward(phenotypes, rotations, translation):
    import roma

    model = load_anny("anny")
    B, J = rotations.shape[0], rotations.shape[1]
    D = torch.zeros(B, J, 4, 4, dtype=torch.float64)
    D[..., :3, :3] = roma.rotvec_to_rotmat(torch.as_tensor(rotations, dtype=torch.float64))
    D[:, 0, :3, 3] = torch.as_tensor(translation, dtype=torch.float64)
    D[..., 3, 3] = 1.0
    with torch.no_grad():
        out = model(pose_parameters=D, phenotype_kwargs=torch.as_tensor(phenotypes, dtype=torch.float64))
    return {k: v.numpy() for k, v in out.items()}


def test_parity_random_phenotypes_and_poses(body):
    rng = np.random.default_rng(0)
    B = 6
    ph = rng.random((B, 6)).astype(np.float32)
    ph[:, 1] = rng.uniform(0.77, 1.0, B)
    ph[0] = NEUTRAL_PHENOTYPES
    ph[1] = [0, 0.77, 0, 0, 0, 0]
    ph[2] = [1, 1, 1, 1, 1, 1]
    rot = (rng.normal(size=(B, body.num_bones, 3)) * 0.4).astype(np.float32)
    trans = rng.normal(size=(B, 3)).astype(np.float32) * 0.3
    ref = _anny_forward(ph, rot, trans)

    shape = body.shape(ph)
    W, T = body.pose(shape.rest_bone_poses, rot[:, None], trans[:, None])
    verts = body.skin(shape.rest_vertices, T)[:, 0]
    np.testing.assert_allclose(shape.rest_vertices, ref["rest_vertices"], atol=1e-5)
    np.testing.assert_allclose(shape.rest_bone_poses, ref["rest_bone_poses"], atol=1e-5)
    np.testing.assert_allclose(W[:, 0], ref["bone_poses"], atol=1e-5)
    err = np.abs(verts - ref["vertices"]).max()
    assert err < 1e-5, f"max vertex error {err:.3g} m"


def test_hm08_vertices_match_anny_full(body):
    rng = np.random.default_rng(1)
    ph = rng.random((3, 6)).astype(np.float32)
    full = load_anny("anny-full")
    with torch.no_grad():
        ref = full(phenotype_kwargs=torch.as_tensor(ph, dtype=torch.float64))["rest_vertices"].numpy()
    got = body.hm08_vertices(body.shape(ph))
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, atol=1e-5)
