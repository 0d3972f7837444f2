"""inference.learned on the shipped models (assets/models): recorded parity, chunked GRU state,
outputs that change with shape and over time, the pipeline's learned stages and the error for
a garment without models. No torch here: the runtime is numpy + onnxruntime."""
from __future__ import annotations

import json

import numpy as np
import pytest

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.errors import UnknownAssetError
from inference.garment import GarmentCatalog
from inference.learned import MODELS_DIR, LearnedGarment, LearnedModels, MissingModelError
from inference.motion.clips import ClipLibrary, adapt_clip
from inference.motion.descriptor import motion_descriptor
from inference.pipeline import DrapeOptions, PoseSequence, drape

CATALOG = GarmentCatalog.load()
PARITY_TOLERANCE = 1e-4  # training.export_onnx.PARITY_TOLERANCE_M
SIZE_LIMIT_BYTES = 20 * 1024 * 1024
CORNER = np.array([[1.0, 1.0, 1.0, 1.0, 1.0, 1.0]], np.float32)
# The garments that ship ch. 4 models (fit regressor + wrinkle GRU). The later catalog garments
# have none: their defaults are the retarget or fit 'canonical', and a request for the learned
# model answers 422 (MissingModelError, test below).
WITH_MODELS = ("dress", "jacket", "longsleeve", "trousers", "tshirt")
# The garments that ship the fit regressor alone, on the geodesic output basis (inference.fit_basis):
# fit 'learned' and 'learned-canonical' run; dynamics 'learned' runs only with fit 'canonical'.
FIT_ONLY = ("crewtee", "croptop", "leggings", "shirt")


@pytest.fixture(scope="module")
def models():
    return LearnedModels()


@pytest.fixture(scope="module")
def walk_gamma():
    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    rot, trans = adapt_clip(ClipLibrary().load("walk"), body, shape)
    return motion_descriptor(rot[:, :24], trans[:, :24], 30.0)


def test_the_garments_without_models_default_to_methods_they_can_run():
    from inference.defaults import default_methods

    table = default_methods()
    others = sorted(set(CATALOG.ids()) - set(WITH_MODELS) - set(FIT_ONLY))
    assert set(WITH_MODELS) | set(FIT_ONLY) <= set(CATALOG.ids()) and others
    for gid in others:
        assert not (MODELS_DIR / gid / "model.json").exists()
        method = table.get(gid)
        assert method.fit in ("retarget", "canonical"), gid
        # dynamics 'learned' with fit 'canonical' runs the garment's learned canonical model, if it ships one
        assert method.dynamics == "none" or (method.fit == "canonical" and (MODELS_DIR / gid / "canonical.json").exists()), gid
        with pytest.raises(MissingModelError):
            LearnedModels().get(gid)


@pytest.mark.parametrize("garment_id", WITH_MODELS)
def test_the_garments_with_models_ship_them(garment_id):
    meta = json.loads((MODELS_DIR / garment_id / "model.json").read_text())
    assert meta["garment"] == garment_id and meta["vertices"] == CATALOG.get(garment_id).num_vertices
    assert meta["fit"]["parity_max_abs_m"] <= PARITY_TOLERANCE
    assert meta["wrinkle"]["parity_max_abs"] <= PARITY_TOLERANCE
    assert meta["fit"]["opset"] >= 17 and meta["wrinkle"]["opset"] >= 17
    assert meta["wrinkle"]["gru_layers"] == 4 and meta["wrinkle"]["gru_hidden"] == 256
    assert "01_01" not in meta["wrinkle"]["config"]["clips"]
    size = sum((MODELS_DIR / garment_id / meta[k]["file"]).stat().st_size for k in ("fit", "wrinkle"))
    assert size <= SIZE_LIMIT_BYTES
    assert meta["fit"]["train_wall_s"] > 0 and meta["wrinkle"]["train_wall_s"] > 0


@pytest.mark.parametrize("garment_id", FIT_ONLY)
def test_the_garments_with_a_fit_alone_ship_a_compact_one(models, garment_id):
    meta = json.loads((MODELS_DIR / garment_id / "model.json").read_text())
    assert meta["garment"] == garment_id and meta["vertices"] == CATALOG.get(garment_id).num_vertices
    assert meta["wrinkle"] is None and not (MODELS_DIR / garment_id / "wrinkle.onnx").exists()
    fit = meta["fit"]
    assert fit["basis"]["kind"] == "geodesic" and len(fit["basis"]["nodes"]) == fit["basis_size"]
    assert fit["parity_max_abs_m"] <= PARITY_TOLERANCE and fit["train_wall_s"] > 0
    assert (MODELS_DIR / garment_id / fit["file"]).stat().st_size <= 1024 * 1024
    lg = models.get(garment_id)
    assert not lg.has_wrinkles and lg.fit_basis.shape == (lg.num_vertices, fit["basis_size"])
    out = lg.fit(np.concatenate([NEUTRAL_PHENOTYPES[None], CORNER]))
    assert out.shape == (2, lg.num_vertices, 3) and out.dtype == np.float32 and np.isfinite(out).all()
    assert np.abs(out[0] - out[1]).max() > 1e-3  # R_G depends on the shape
    assert np.abs(out).max() < 0.3  # a fit, not a spike


def test_a_fit_alone_refuses_the_learned_dynamics_by_field(models):
    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    rot, trans = adapt_clip(ClipLibrary().load("walk"), body, shape)
    motion = PoseSequence(rot[0, :3], trans[0, :3], 30.0)
    garment = [CATALOG.get(FIT_ONLY[0])]
    with pytest.raises(MissingModelError) as err:
        drape(body, shape, motion, garment, DrapeOptions(fit="learned", dynamics="learned", guard=False), models=models)
    assert err.value.field == "/options/dynamics"
    fitted = drape(body, shape, motion, garment, DrapeOptions(fit="learned-canonical", dynamics="none"), models=models)
    assert np.isfinite(fitted.garments[0].vertices).all()


@pytest.mark.parametrize("garment_id", WITH_MODELS)
def test_outputs_change_with_shape_and_over_time(models, walk_gamma, garment_id):
    lg = models.get(garment_id)
    p = np.concatenate([NEUTRAL_PHENOTYPES[None], CORNER])
    fit = lg.fit(p)
    assert fit.shape == (2, lg.num_vertices, 3) and fit.dtype == np.float32
    assert np.abs(fit[0] - fit[1]).max() > 1e-4  # R_G depends on the shape
    gamma = np.repeat(walk_gamma, 2, axis=0)
    delta, _ = lg.wrinkles(p, gamma)
    assert delta.shape == (2, gamma.shape[1], lg.num_vertices, 3) and np.isfinite(delta).all()
    assert np.abs(delta[0, 10] - delta[0, 20]).max() > 1e-5  # R_L changes over time
    assert np.abs(delta[0] - delta[1]).max() > 1e-5  # ... and with the shape


def test_chunked_state_equals_one_call(models, walk_gamma):
    lg = models.get("tshirt")
    p = np.array([[0.2, 0.9, 0.7, 0.3, 0.6, 0.4]], np.float32)
    full, h_full = lg.wrinkles(p, walk_gamma)
    a, h_a = lg.wrinkles(p, walk_gamma[:, :10])
    b, h_b = lg.wrinkles(p, walk_gamma[:, 10:], h_a)
    np.testing.assert_allclose(np.concatenate([a, b], 1), full, atol=1e-5)
    np.testing.assert_allclose(h_b, h_full, atol=1e-5)


def test_batch_consistency(models, walk_gamma):
    lg = models.get("trousers")
    p = np.concatenate([NEUTRAL_PHENOTYPES[None], CORNER, CORNER * 0.9])
    p[:, 1] = np.maximum(p[:, 1], 0.77)
    g = np.repeat(walk_gamma[:, :6], 3, axis=0)
    fit = lg.fit(p)
    delta, _ = lg.wrinkles(p, g)
    for i in range(3):
        np.testing.assert_allclose(lg.fit(p[i : i + 1])[0], fit[i], atol=1e-6)
        np.testing.assert_allclose(lg.wrinkles(p[i : i + 1], g[i : i + 1])[0][0], delta[i], atol=1e-5)


def test_input_shapes_are_checked(models):
    lg = models.get("tshirt")
    with pytest.raises(ValueError, match="phenotypes"):
        lg.fit(np.zeros((2, 5), np.float32))
    with pytest.raises(ValueError, match="gamma"):
        lg.wrinkles(np.zeros((1, 6), np.float32), np.zeros((1, 3, 10), np.float32))
    with pytest.raises(ValueError, match="h0"):
        lg.wrinkles(np.zeros((1, 6), np.float32), np.zeros((1, 3, lg.descriptor_size), np.float32), np.zeros((1, 1, 1), np.float32))


def test_missing_models_raise_a_specific_error(tmp_path):
    registry = LearnedModels(tmp_path)
    assert not registry.available("tshirt")
    with pytest.raises(MissingModelError, match="no learned models") as err:
        registry.get("tshirt", "/options/fit")
    assert isinstance(err.value, UnknownAssetError) and err.value.field == "/options/fit"
    with pytest.raises(MissingModelError):
        LearnedGarment.load(tmp_path / "tshirt")


def test_pipeline_learned_stages(models):
    body = BodyModel.load()
    shape = body.shape(CORNER)
    clip = ClipLibrary().load("walk")
    rot, trans = adapt_clip(clip, body, shape)
    motion = PoseSequence(rot[0, :12], trans[0, :12], clip.fps)
    garments = [CATALOG.get("tshirt"), CATALOG.get("trousers")]
    options = dict(guard=False)
    learned = drape(body, shape, motion, garments, DrapeOptions(fit="learned", dynamics="learned", **options), models=models)
    fit_only = drape(body, shape, motion, garments, DrapeOptions(fit="learned", dynamics="none", **options), models=models)
    retarget = drape(body, shape, motion, garments, DrapeOptions(fit="retarget", dynamics="none", **options), models=models)
    # None: each garment's own default (inference.defaults, tests/test_defaults.py); any method stays selectable
    assert DrapeOptions().fit is None and DrapeOptions().dynamics is None
    for a, b, c in zip(learned.garments, fit_only.garments, retarget.garments):
        assert a.vertices.shape == c.vertices.shape == (12, a.asset.num_vertices, 3)
        assert np.abs(a.vertices - b.vertices).max() > 1e-5  # R_L applied
        assert np.abs(b.vertices - c.vertices).max() > 1e-5  # R_G applied
        assert np.isfinite(a.vertices).all()
    with pytest.raises(MissingModelError):
        drape(body, shape, motion, garments, DrapeOptions(dynamics="learned", fit="retarget", **options), models=LearnedModels(MODELS_DIR / "nowhere"))


def test_segments_restart_the_dynamics_per_motion(models):
    """Cross-request batching: two motions concatenated with ``segments`` give each motion's own
    result (descriptor and GRU restart at the second motion's first frame)."""
    from inference.errors import InputShapeError

    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    walk, run = ClipLibrary().load("walk"), ClipLibrary().load("run")
    (rw, tw), (rr, tr) = adapt_clip(walk, body, shape), adapt_clip(run, body, shape)
    a, b = PoseSequence(rw[0, :9], tw[0, :9], 30.0), PoseSequence(rr[0, 5:12], tr[0, 5:12], 30.0)
    both = PoseSequence(np.concatenate([a.rotations, b.rotations]), np.concatenate([a.translation, b.translation]), 30.0)
    garments = [CATALOG.get("tshirt")]
    options = DrapeOptions(fit="learned", dynamics="learned", guard=False)
    solo = [drape(body, shape, m, garments, options, models=models).garments[0].vertices for m in (a, b)]
    merged = drape(body, shape, both, garments, options, models=models, segments=[9, 7]).garments[0].vertices
    np.testing.assert_allclose(merged, np.concatenate(solo), atol=1e-5)
    unsegmented = drape(body, shape, both, garments, options, models=models).garments[0].vertices
    assert np.abs(unsegmented[9:] - solo[1]).max() > 1e-4  # without segments the GRU state would leak
    with pytest.raises(InputShapeError):
        drape(body, shape, both, garments, options, models=models, segments=[9, 8])
