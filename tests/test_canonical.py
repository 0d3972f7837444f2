"""fit 'canonical' (thesis ch. 6): the shipped diffused body, the canonical push, the pipeline."""
import numpy as np
import pytest

from inference.body import BodyModel
from inference.canonical import CanonicalModels, push_out
from inference.errors import UnknownAssetError
from inference.garment import GarmentCatalog
from inference.mesh import vertex_normals
from inference.metrics import inside_mask
from inference.motion.clips import ClipLibrary
from inference.options import DrapeOptions
from inference.pipeline import PoseSequence, drape

HEAVY = np.ones((1, 6), np.float32)


@pytest.fixture(scope="module")
def setup():
    return BodyModel.load(), GarmentCatalog.load(), CanonicalModels()


def test_push_out_moves_only_points_within_the_margin_and_leaves_them_at_it(setup):
    body, _, canonical = setup
    d = canonical.diffused
    rng = np.random.default_rng(0)
    # skin points of the torso and limbs (where garments are), jittered, and the same 10 cm out
    covered = np.isin(body.dense_weights.argmax(1), [body.bone_names.index(b) for b in
                                                     ("Spine", "Spine1", "LowerBack", "LeftArm", "RightArm", "LeftUpLeg", "RightUpLeg")])
    ids = rng.choice(np.flatnonzero(covered), 400)
    n = vertex_normals(d.neutral_vertices[None], body.faces)[0, ids]
    V = d.neutral_vertices[ids]
    X = np.concatenate([V + rng.normal(0.0, 0.004, V.shape), V + 0.1 * n]).astype(np.float32)
    before = d.sdf(X)
    Y, moved = push_out(d, X, 0.003)
    after = d.sdf(Y)
    assert moved == int((before < 0.003).sum()) > 50
    assert after.min() > 0.003 - 5e-4
    far = before >= 0.003
    np.testing.assert_array_equal(Y[far], X[far])


def test_canonical_fit_keeps_the_garment_out_of_shaped_bodies_where_the_retarget_does_not(setup):
    """T_G(X, beta) = X + B~s(X, beta) (eq. 6.8) of the T-shirt on the heaviest adult, in the rest
    pose: the diffused offsets carry every point with its skin (measured 0.02 % inside), the
    .mhclo retarget scales the garment per axis (2.8 % inside)."""
    body, catalog, canonical = setup
    asset = catalog.get("tshirt")
    shape = body.shape(HEAVY)
    fit, weights = canonical.rest_fit(asset, shape.rest_vertices[0])
    inside = inside_mask(fit[None], shape.rest_vertices, body.faces)[0].mean()
    retarget = asset.retarget_fit(body.hm08_vertices(shape))
    inside_retarget = inside_mask(retarget, shape.rest_vertices, body.faces)[0].mean()
    assert inside <= 0.001 < inside_retarget
    assert np.allclose(weights.sum(1), 1.0, atol=1e-5) and (weights >= 0).all()


def test_a_lone_canonical_garment_runs_the_exact_stage_alone_and_ends_outside_the_body(setup):
    body, catalog, canonical = setup
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:4], clip.translation[:4], clip.fps)
    shape = body.shape(HEAVY)
    r = drape(body, shape, motion, [catalog.get("tshirt")], DrapeOptions(fit="canonical", dynamics="none"), canonical=canonical)
    assert "guard" not in r.timings_ms and "repair" in r.timings_ms
    assert not inside_mask(r.garments[0].vertices, r.body_vertices, body.faces).any()
    off = drape(body, shape, motion, [catalog.get("tshirt")], DrapeOptions(fit="canonical", dynamics="none", collisions="off"), canonical=canonical)
    assert "repair" not in off.timings_ms
    # the final stage moves only the few points it must
    moved = np.linalg.norm(r.garments[0].vertices - off.garments[0].vertices, axis=-1) > 0
    assert moved.mean() < 0.05


def test_canonical_with_learned_dynamics_is_refused_naming_the_field(setup):
    body, catalog, canonical = setup
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:2], clip.translation[:2], clip.fps)
    with pytest.raises(UnknownAssetError) as e:
        drape(body, body.shape(HEAVY), motion, [catalog.get("tshirt")], DrapeOptions(fit="canonical", dynamics="learned"), canonical=canonical)
    assert e.value.field == "/options/dynamics"
