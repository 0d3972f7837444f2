"""fit 'canonical' (thesis ch. 6): the shipped diffused body, the canonical push, the pipeline."""
import numpy as np
import pytest

from inference.body import BodyModel
from inference.canonical import PUSH_TOLERANCE_M, CanonicalModels, push_fields, push_out
from inference.defaults import Method, default_methods
from inference.learned import MissingModelError
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
    assert moved == int((before < 0.003 - PUSH_TOLERANCE_M).sum()) > 50
    assert after.min() > 0.003 - 5e-4
    far = before >= 0.003 - PUSH_TOLERANCE_M
    np.testing.assert_array_equal(Y[far], X[far])
    # the one-gather form the pipeline runs: the same points, and the fields eq. 6.7 reads at them
    Z, fields, none = push_fields(d, X.reshape(2, -1, 3), 0.003)
    assert none is None
    np.testing.assert_array_equal(Z.reshape(-1, 3), Y)
    np.testing.assert_array_equal(fields, d.fields(Y).reshape(2, -1, fields.shape[-1]))
    np.testing.assert_array_equal(fields[..., -1].ravel(), after)
    # with a body's offsets: B~s at the pushed points from the same pass, bitwise its own read
    offsets = d.offsets(d.neutral_vertices + np.float32(0.01))
    Z2, fields2, shape_offsets = push_fields(d, X.reshape(2, -1, 3), 0.003, offsets)
    np.testing.assert_array_equal(Z2, Z)
    np.testing.assert_array_equal(fields2, fields)
    np.testing.assert_array_equal(shape_offsets, d.shape_offsets(Y, offsets).reshape(2, -1, 3))


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
    # kept per garment and body: the same (read-only) fit for an equal body, another for another
    again, _ = canonical.rest_fit(asset, shape.rest_vertices[0].copy())
    assert again is fit and not fit.flags.writeable
    other, _ = canonical.rest_fit(asset, body.shape(np.full((1, 6), 0.5, np.float32)).rest_vertices[0])
    X, _, S = canonical._static(asset)
    neutral = canonical.diffused.neutral_vertices
    np.testing.assert_array_equal(fit, (X + S @ (shape.rest_vertices[0] - neutral)).astype(np.float32))
    assert not np.array_equal(other, fit)


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


def test_canonical_with_learned_dynamics_needs_a_learned_canonical_model(setup, tmp_path):
    body, catalog, _ = setup
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:2], clip.translation[:2], clip.fps)
    canonical = CanonicalModels(models_dir=tmp_path)  # no garment ships one here
    with pytest.raises(UnknownAssetError) as e:
        drape(body, body.shape(HEAVY), motion, [catalog.get("tshirt")], DrapeOptions(fit="canonical", dynamics="learned"), canonical=canonical)
    assert e.value.field == "/options/dynamics"


@pytest.fixture(scope="module")
def learned_dir(setup, tmp_path_factory):
    """A small canonical model of the T-shirt, trained here (VAE of eq. 6.13-6.16 on canonical
    frames that breathe out with the walk's phase, regressor of eq. 6.17-6.18 onto their
    encodings) and written as the runtime reads it (``train_canonical.write_model_json``)."""
    torch = pytest.importorskip("torch")
    from inference.motion.descriptor import motion_descriptor
    from training.canonical_regressor import RegressorConfig, export_regressor, train_regressor
    from training.canonical_vae import VAEConfig, export_decoder, metadata_record, train_vae
    from training.train_canonical import write_model_json

    body, catalog, canonical = setup
    asset = catalog.get("tshirt")
    clip = ClipLibrary().load("walk")
    gamma = motion_descriptor(clip.rotations[None, :24], clip.translation[None, :24], clip.fps)[0]
    n = vertex_normals(asset.vertices[None], asset.faces)[0]
    amp = (0.006 * (1.0 + np.sin(np.arange(24) * 0.5)))[:, None, None].astype(np.float32)
    frames = (asset.vertices[None] + amp * n[None]).astype(np.float32)
    vae, vae_record = train_vae(frames, asset.vertices, asset.faces, asset.edges, canonical.diffused,
                                VAEConfig(latent=4, basis=16, hidden=32, batch=4, random_batch=2, steps_reconstruction=60, steps_collision=20))
    with torch.no_grad():
        z = vae.encode(torch.as_tensor(frames))[0].numpy()
    seqs = [{"phenotypes": p, "gamma": gamma, "z": z} for p in (HEAVY[0], np.full(6, 0.5, np.float32))]
    reg, reg_record = train_regressor(seqs, 4, RegressorConfig(hidden=16, layers=2, steps=80, window=24, batch=2))
    out = tmp_path_factory.mktemp("models") / "tshirt"
    out.mkdir()
    vae_record["export"] = export_decoder(vae, out / "canonical_decoder.onnx", metadata_record(vae_record))
    reg_record["export"] = export_regressor(reg, out / "canonical_regressor.onnx")
    write_model_json(out, asset, vae_record, reg_record, ["synthetic"])
    return out.parent


def test_learned_canonical_frames_are_decoded_per_frame_and_end_outside_the_body(setup, learned_dir):
    from inference.pipeline import drape_chunks

    body, catalog, _ = setup
    canonical = CanonicalModels(models_dir=learned_dir)
    assert canonical.available("tshirt") and not canonical.available("jacket")
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:8], clip.translation[:8], clip.fps)
    shape = body.shape(HEAVY)
    options = DrapeOptions(fit="canonical", dynamics="learned", lift_arms=False)
    r = drape(body, shape, motion, [catalog.get("tshirt")], options, canonical=canonical)
    v = r.garments[0].vertices
    assert v.shape == (8, catalog.get("tshirt").num_vertices, 3) and np.isfinite(v).all()
    assert not inside_mask(v, r.body_vertices, body.faces).any()
    # the canonical form changes from frame to frame (the decoded X_t, not a fixed template)
    X, _ = canonical.frames(catalog.get("tshirt"), shape.phenotypes, r_gamma(motion), [8])
    assert np.linalg.norm(X[1:] - X[:-1], axis=-1).max() > 1e-4
    assert canonical.diffused.sdf(X).min() > 0.003 - 5e-4  # pushed out to the garment's margin
    # in chunks, the regressor's state carried: the same frames (before the final stage, whose
    # discrete choices, inside or not and which target is nearest, may flip for a vertex at a tie
    # when the carried state differs from the whole sequence's by float rounding: seen once in CI,
    # one vertex of 20,592 moved 0.6 mm)
    raw = options.replace(collisions="off")
    whole = drape(body, shape, motion, [catalog.get("tshirt")], raw, canonical=canonical).garments[0].vertices
    parts = [p.garments[0].vertices for _, p in drape_chunks(body, shape, motion, [catalog.get("tshirt")], raw, chunk_frames=3,
                                                            canonical=canonical)]
    np.testing.assert_allclose(np.concatenate(parts), whole, atol=1e-4)
    assert np.linalg.norm(whole - v, axis=-1).max() > 0  # the final stage moved something there
    # a garment without a learned canonical model is refused, naming the field
    with pytest.raises(UnknownAssetError) as e:
        drape(body, shape, motion, [catalog.get("jacket")], options, canonical=canonical)
    assert e.value.field == "/options/dynamics"


def r_gamma(motion: PoseSequence) -> np.ndarray:
    from inference.motion.descriptor import motion_descriptor

    return motion_descriptor(motion.rotations[None], motion.translation[None], motion.fps)


def test_a_layered_canonical_outfit_keeps_the_layer_pushes_and_ends_outside_the_body(setup, monkeypatch):
    import inference.pipeline as pipeline

    body, catalog, canonical = setup
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:3], clip.translation[:3], clip.fps)
    seen = []
    real = pipeline.guard_layers
    monkeypatch.setattr(pipeline, "guard_layers", lambda *a, **k: (seen.append((k["check"], len(a[2].body))), real(*a, **k))[1])
    r = drape(body, body.shape(HEAVY), motion, [catalog.get("tshirt"), catalog.get("jacket")], DrapeOptions(fit="canonical", dynamics="none"),
              canonical=canonical)
    assert "guard" in r.timings_ms and "repair" in r.timings_ms
    # every layer pushed, without the closest-triangle check: it is for posed-space garments (the
    # exact stage follows here)
    assert seen == [(False, 2)]
    for g in r.garments:
        assert not inside_mask(g.vertices, r.body_vertices, body.faces).any()


def test_a_learned_canonical_model_covers_the_bodies_near_its_training_bodies(setup, tmp_path):
    import json

    from inference.canonical import BODY_RANGE, BODY_RANGE_BY_CATEGORY

    _, catalog, canonical = setup
    tshirt, trousers = catalog.get("tshirt"), catalog.get("trousers")
    # the shipped models' record: their four training bodies (training.protocol.BODIES)
    train = canonical.train_phenotypes("tshirt")
    assert train.shape == (4, 6)
    assert canonical.covers(tshirt, HEAVY) and canonical.covers(trousers, train[2])
    step = np.array([1, -1, 1, -1, 1, -1], np.float32) / np.sqrt(6)  # a unit step in phenotype space
    top, other = BODY_RANGE_BY_CATEGORY["top"], BODY_RANGE
    assert canonical.covers(tshirt, train[0] + 0.9 * top * step) and not canonical.covers(tshirt, train[0] + 1.1 * top * step)
    assert canonical.covers(trousers, train[0] + 0.9 * other * step) and not canonical.covers(trousers, train[0] + 1.1 * other * step)
    # a model without a record of its bodies covers every body; no model, no range
    (tmp_path / "tshirt").mkdir()
    (tmp_path / "tshirt" / "canonical.json").write_text(json.dumps({"garment": "tshirt", "train_cases": ["synthetic"]}))
    bare = CanonicalModels(models_dir=tmp_path)
    far = np.array([0.0, 1.0, 0.0, 0.0, 1.0, 1.0], np.float32)  # an old, tall, thin woman
    assert bare.train_phenotypes("tshirt") is None and bare.covers(tshirt, far) and bare.train_phenotypes("jacket") is None


def test_the_default_drape_of_a_body_beyond_the_range_runs_the_beyond_range_method(setup):
    body, catalog, canonical = setup
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:2], clip.translation[:2], clip.fps)
    far = np.array([[0.0, 1.0, 0.0, 0.0, 1.0, 1.0]], np.float32)  # no training body near
    tshirt = catalog.get("tshirt")
    assert not canonical.covers(tshirt, far[0]) and canonical.covers(tshirt, HEAVY[0])
    options = DrapeOptions(lift_arms=False)
    beyond = default_methods().get("tshirt").beyond_range  # the shipped table's, else the static canonical form
    expected = beyond.method if beyond is not None else Method("canonical", "none")
    r = drape(body, body.shape(far), motion, [tshirt], options, canonical=canonical)
    assert r.garments[0].method == expected
    r = drape(body, body.shape(HEAVY), motion, [tshirt], options, canonical=canonical)
    assert (r.garments[0].method.fit, r.garments[0].method.dynamics) == ("canonical", "learned")
    # asked for by name, the learned model runs on any body
    r = drape(body, body.shape(far), motion, [tshirt], options.replace(dynamics="learned"), canonical=canonical)
    assert r.garments[0].method.dynamics == "learned"


def test_learned_canonical_keeps_the_one_size_garment_from_stretching_with_a_tall_body(setup):
    """fit 'learned-canonical': the fit regressor's garment (trained on sampled bodies with the one
    rest geometry), skinned by the diffused body's W~ and through the final exact stage alone.
    On a tall, thin body B~s stretches the static canonical T-shirt with the body (edge p99 ~1.9 on
    the validation walk, newton's ~1.5); the regressor's keeps it shorter; no vertex ends inside."""
    body, catalog, canonical = setup
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:3], clip.translation[:3], clip.fps)
    far = body.shape(np.array([[0.0, 1.0, 0.0, 0.0, 1.0, 1.0]], np.float32))
    tshirt = catalog.get("tshirt")
    options = DrapeOptions(dynamics="none", lift_arms=False)
    learned = drape(body, far, motion, [tshirt], options.replace(fit="learned-canonical"), canonical=canonical)
    static = drape(body, far, motion, [tshirt], options.replace(fit="canonical"), canonical=canonical)
    assert learned.garments[0].method == Method("learned-canonical", "none")

    def p99(v):
        e = tshirt.edges
        rest = np.linalg.norm(tshirt.rest_vertices[e[:, 0]] - tshirt.rest_vertices[e[:, 1]], axis=-1)
        return np.percentile(np.linalg.norm(v[:, e[:, 0]] - v[:, e[:, 1]], axis=-1) / rest, 99)

    assert p99(learned.garments[0].vertices) < p99(static.garments[0].vertices) - 0.1
    assert not inside_mask(learned.garments[0].vertices, learned.body_vertices, body.faces).any()
    # the posed-space guard's pushes do not run (a lone canonical-space garment)
    assert "guard" not in learned.timings_ms and "repair" in learned.timings_ms
    # a garment without a fit regressor: a 4xx naming the option
    with pytest.raises(MissingModelError, match="suittrousers") as err:
        drape(body, far, motion, [catalog.get("suittrousers")], options.replace(fit="learned-canonical"), canonical=canonical)
    assert err.value.field == "/options/fit"


def test_the_default_blends_across_the_edge_of_the_body_range(setup):
    """Within BLEND_BAND of the T-shirt's range the default drape is (1 - w) x the learned model's
    + w x the beyond-range method's (collision stages off: nothing moves them after), w a
    smoothstep from 0 to 1 across the band, 0.5 at the range."""
    from inference.canonical import BLEND_BAND, BODY_RANGE_BY_CATEGORY

    body, catalog, canonical = setup
    tshirt = catalog.get("tshirt")
    train = canonical.train_phenotypes("tshirt")
    r = BODY_RANGE_BY_CATEGORY["top"]
    away = np.array([0.0, 0.0, 0.0, -1.0, 0.0, 0.0], np.float32)  # lighter than the neutral training body

    def at(d):
        return (train[0] + d * away)[None]

    assert canonical.beyond_weight(tshirt, at(0.0)) == 0.0 and canonical.beyond_weight(tshirt, at(r * (1 - BLEND_BAND))) == 0.0
    assert canonical.beyond_weight(tshirt, at(r)) == pytest.approx(0.5, abs=1e-3)
    assert canonical.beyond_weight(tshirt, at(r * (1 + BLEND_BAND) + 1e-3)) == 1.0
    w = [canonical.beyond_weight(tshirt, at(d)) for d in np.linspace(0.2, 0.5, 13)]
    assert all(b >= a for a, b in zip(w, w[1:]))  # monotone
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:3], clip.translation[:3], clip.fps)
    shape = body.shape(at(r * 0.95))
    off = DrapeOptions(lift_arms=False, collisions="off")
    blended = drape(body, shape, motion, [tshirt], off, canonical=canonical)
    m = blended.garments[0].method
    beyond = default_methods().get("tshirt").beyond_range
    assert m.beyond == (beyond.method if beyond is not None else Method("canonical", "none")) and 0.0 < m.beyond_weight < 0.5
    own = drape(body, shape, motion, [tshirt], off.replace(fit="canonical", dynamics="learned"), canonical=canonical).garments[0].vertices
    other = drape(body, shape, motion, [tshirt], off.replace(fit=m.beyond.fit, dynamics=m.beyond.dynamics), canonical=canonical).garments[0].vertices
    np.testing.assert_allclose(blended.garments[0].vertices, (1 - m.beyond_weight) * own + m.beyond_weight * other, atol=1e-6)
    assert np.abs(own - other).max() > 0.01  # the two differ: the blend is what smooths the edge
    # with the collision stages, no vertex inside the body
    full = drape(body, shape, motion, [tshirt], DrapeOptions(lift_arms=False), canonical=canonical)
    assert full.garments[0].method == m and not inside_mask(full.garments[0].vertices, full.body_vertices, body.faces).any()
