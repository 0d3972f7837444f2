"""The diffused body model (thesis eq. 6.4-6.5) built on a coarse grid and read back."""
import numpy as np
import pytest

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.diffused import DiffusedBody, Grid
from inference.mesh import vertex_normals
from training.assets import build_diffused_body as bdb


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    arrays, report = bdb.build(spacing_m=0.05, shape_spacing_m=0.08, samples=8, workers=1, residual_m=0.01)
    path = tmp_path_factory.mktemp("diffused") / "diffused.npz"
    import json
    np.savez_compressed(path, metadata=np.array(json.dumps(report)), **arrays)
    return DiffusedBody.load(path), report


def test_trilinear_grid_reproduces_a_linear_field_exactly():
    g = np.stack(np.meshgrid(np.arange(4), np.arange(5), np.arange(6), indexing="ij"), -1).astype(np.float32)
    f = (g @ np.array([1.0, -2.0, 0.5], np.float32))[..., None] * 0.1
    grid = Grid(np.zeros(3), 0.1, f.astype(np.float32))
    p = np.random.default_rng(0).uniform(0.0, 0.3, (100, 3)).astype(np.float32)
    np.testing.assert_allclose(grid.interpolate(p)[:, 0], p @ np.array([1.0, -2.0, 0.5]), atol=1e-5)


def test_diffused_fields_match_the_body_at_its_surface(built):
    diffused, report = built
    body = BodyModel.load()
    neutral = body.shape(NEUTRAL_PHENOTYPES[None])
    V = neutral.rest_vertices[0]
    n = vertex_normals(neutral.rest_vertices, body.faces)[0]
    torso = np.isin(body.dense_weights.argmax(1), [body.bone_names.index(b) for b in ("Spine", "Spine1", "LowerBack")])
    w = diffused.weights(V[torso])
    assert np.allclose(w.sum(1), 1.0, atol=1e-5) and (w >= 0).all()
    assert np.abs(w - body.dense_weights[torso]).sum(1).mean() < 0.3
    # the sign of the SDF: 3 cm outside the torso positive, 3 cm inside negative
    assert (diffused.sdf(V[torso] + 0.03 * n[torso]) > 0).mean() > 0.99
    assert (diffused.sdf(V[torso] - 0.03 * n[torso]) < 0).mean() > 0.99
    # shape offsets near the surface follow the body's: heavy adult, torso vertices
    heavy = body.shape(np.array([[1.0, 1.0, 1.0, 1.0, 1.0, 1.0]], np.float32))
    truth = heavy.rest_vertices[0, torso] - V[torso]
    got = diffused.shape_offsets(V[None, torso], heavy.coeffs)[0]
    err = np.linalg.norm(got - truth, axis=1)
    assert err.mean() < 0.3 * np.linalg.norm(truth, axis=1).mean() and err.mean() < 0.01
    assert report["shape"]["residual_max_m"] <= 0.01


def test_deshaped_to_shaped_is_the_identity_on_the_neutral_body(built):
    diffused, _ = built
    body = BodyModel.load()
    neutral = body.shape(NEUTRAL_PHENOTYPES[None])
    X = neutral.rest_vertices[:, ::50] + 0.01
    shaped, w = diffused.deshaped_to_shaped(X, neutral.coeffs)
    np.testing.assert_allclose(shaped, X, atol=1e-5)
    assert w.shape == X.shape[:2] + (body.num_bones,)
