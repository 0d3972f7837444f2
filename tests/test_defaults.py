"""inference.defaults: each garment's default method (assets/models/defaults.json), its
validation, and the pipeline's per-garment resolution (a request's fit / dynamics, else the
garment's default)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from inference.body import ASSETS_DIR, NEUTRAL_PHENOTYPES, BodyModel
from inference.defaults import (DEFAULTS_FILE, BeyondRange, DefaultMethod, DefaultMethods, DefaultMethodsError, Method, default_methods,
                                resolve_methods)
from inference.errors import InputValueError
from inference.garment import GarmentCatalog, catalog_ids
from inference.learned import LearnedModels
from inference.motion.clips import ClipLibrary, adapt_clip
from inference.pipeline import DrapeOptions, PoseSequence, drape

ENTRY = {"reason": "a test table", "evidence": "tests/test_defaults.py"}
# trousers keep the learned model, the T-shirt ships the baseline: one drape layers both
MIXED = DefaultMethods({"trousers": DefaultMethod("learned", "learned", **ENTRY), "tshirt": DefaultMethod("retarget", "none", **ENTRY)})


def _shipped() -> dict:
    return json.loads((ASSETS_DIR / DEFAULTS_FILE).read_text())


@pytest.fixture(scope="module")
def scene():
    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    rot, trans = adapt_clip(ClipLibrary().load("walk"), body, shape)
    catalog = GarmentCatalog.load()
    return body, shape, PoseSequence(rot[0, :6], trans[0, :6], 30.0), catalog, LearnedModels()


def test_shipped_file_names_every_catalog_garment_with_a_valid_method():
    table = default_methods()
    assert set(table.as_dict()) == set(catalog_ids()) == set(GarmentCatalog.load().ids())
    assert table.as_dict() == _shipped()["garments"]  # the file, entry for entry
    for gid in catalog_ids():
        entry = table.get(gid)
        assert entry.fit in ("canonical", "learned-canonical", "learned", "retarget") and entry.dynamics in ("learned", "none") and entry.reason and entry.evidence
        if entry.beyond_range is not None:  # only beside a default with a body range
            assert entry.method == Method("canonical", "learned") and entry.beyond_range.reason


@pytest.mark.parametrize("change, message", [
    (lambda d: d["garments"].update(cape=dict(d["garments"]["tshirt"])), "unknown garment ids \\['cape'\\]"),
    (lambda d: d["garments"].pop("dress"), "no default method for garments \\['dress'\\]"),
    (lambda d: d["garments"]["tshirt"].update(fit="none"), "garments.tshirt: fit 'none' is not a default fit"),
    (lambda d: d["garments"]["tshirt"].update(fit="simulated"), "garments.tshirt: fit 'simulated'"),
    (lambda d: d["garments"]["jacket"].update(dynamics="retarget"), "garments.jacket: dynamics 'retarget'"),
    (lambda d: d["garments"]["jacket"].update(reason=""), "garments.jacket: reason must be a non-empty string"),
    (lambda d: d["garments"]["jacket"].pop("evidence"), "garments.jacket: expected the keys"),
    (lambda d: d["garments"]["jacket"].update(beyond_range={"fit": "canonical", "dynamics": "none", "reason": "r"}),
     "garments.jacket: beyond_range goes only with fit 'canonical' and dynamics 'learned'"),
    (lambda d: d["garments"]["tshirt"].update(fit="canonical", dynamics="learned", beyond_range={"fit": "none", "dynamics": "none", "reason": "r"}),
     "garments.tshirt.beyond_range: fit 'none' is not a default fit"),
    (lambda d: d["garments"]["tshirt"].update(fit="canonical", dynamics="learned", beyond_range={"fit": "canonical"}),
     "garments.tshirt.beyond_range: expected exactly the keys"),
    (lambda d: d.update(format=2), "format 2, expected 1"),
])
def test_a_bad_file_fails_loudly(tmp_path, change, message):
    data = _shipped()
    change(data)
    path = tmp_path / "defaults.json"
    path.write_text(json.dumps(data))
    with pytest.raises(DefaultMethodsError, match=message) as err:
        DefaultMethods.load(path, catalog_ids())
    assert str(path) in str(err.value)


def test_a_missing_or_unparseable_file_fails_loudly(tmp_path):
    with pytest.raises(DefaultMethodsError, match="cannot read"):
        DefaultMethods.load(tmp_path / "nowhere.json", catalog_ids())
    (tmp_path / "broken.json").write_text('{"format": 1, "garments": {')
    with pytest.raises(DefaultMethodsError, match="not valid JSON"):
        DefaultMethods.load(tmp_path / "broken.json", catalog_ids())


def test_resolution_per_garment_and_explicit_overrides():
    ids = ["trousers", "tshirt"]
    assert resolve_methods(ids, None, None, MIXED) == [Method("learned", "learned"), Method("retarget", "none")]
    # an explicit option applies to every garment; the other one still follows each default
    assert resolve_methods(ids, "learned", None, MIXED) == [Method("learned", "learned"), Method("learned", "none")]
    assert resolve_methods(ids, None, "none", MIXED) == [Method("learned", "none"), Method("retarget", "none")]
    assert resolve_methods(ids, "none", "none", MIXED) == [Method("none", "none")] * 2  # fit 'none': explicit, uniform
    assert resolve_methods(["cape"], "retarget", "none", None) == [Method("retarget", "none")]  # no table needed
    with pytest.raises(DefaultMethodsError, match="no default method for garment 'cape'"):
        resolve_methods(["cape"], None, "none", MIXED)
    with pytest.raises(InputValueError, match="/options/fit"):
        resolve_methods(ids, "simulated", None, MIXED)
    with pytest.raises(DefaultMethodsError, match="fit 'none' is not a default fit"):
        DefaultMethod("none", "none", **ENTRY)


def test_a_body_beyond_the_learned_canonical_models_range_gets_the_static_canonical_form():
    table = DefaultMethods({"trousers": DefaultMethod("canonical", "learned", **ENTRY), "tshirt": DefaultMethod("learned", "learned", **ENTRY)})
    ids = ["trousers", "tshirt"]
    far = lambda g: 1.0  # noqa: E731 - no learned model covers this body
    assert resolve_methods(ids, None, None, table, beyond=lambda g: 0.0) == [Method("canonical", "learned"), Method("learned", "learned")]
    # only the canonical-learned default falls back; the ch. 4 models have no body range
    assert resolve_methods(ids, None, None, table, beyond=far) == [Method("canonical", "none"), Method("learned", "learned")]
    # an explicit dynamics is what the request asked for: never changed
    assert resolve_methods(ids, None, "learned", table, beyond=far) == [Method("canonical", "learned"), Method("learned", "learned")]
    # the fit named, the dynamics left to the default ('learned'): still beyond the range
    assert resolve_methods(ids, "canonical", None, table, beyond=far) == [Method("canonical", "none")] * 2


def test_a_body_beyond_the_range_runs_the_entrys_beyond_range_method():
    beyond = BeyondRange("learned-canonical", "none", "closest on the bodies split")
    table = DefaultMethods({"trousers": DefaultMethod("canonical", "learned", **ENTRY),
                            "tshirt": DefaultMethod("canonical", "learned", beyond_range=beyond, **ENTRY)})
    ids = ["trousers", "tshirt"]
    far = lambda g: 1.0  # noqa: E731
    assert resolve_methods(ids, None, None, table, beyond=lambda g: 0.0) == [Method("canonical", "learned")] * 2
    assert resolve_methods(ids, None, None, table, beyond=far) == [Method("canonical", "none"), Method("learned-canonical", "none")]
    # a request that names the fit or the dynamics gets what it names
    assert resolve_methods(ids, "canonical", None, table, beyond=far) == [Method("canonical", "none")] * 2
    assert resolve_methods(ids, None, "learned", table, beyond=far) == [Method("canonical", "learned")] * 2
    assert table.as_dict()["tshirt"]["beyond_range"] == {"fit": "learned-canonical", "dynamics": "none", "reason": "closest on the bodies split"}
    assert "beyond_range" not in table.as_dict()["trousers"]
    round_trip = DefaultMethods.from_json({"format": 1, "garments": table.as_dict()}, ids)
    assert round_trip.as_dict() == table.as_dict()


def test_pipeline_runs_each_garment_its_default(scene):
    """A drape layering a learned garment with a retargeted one gives each the vertices of an
    explicit drape with that garment's method (guard off: the garments are then independent)."""
    body, shape, motion, catalog, models = scene
    garments = [catalog.get("trousers"), catalog.get("tshirt")]
    base = dict(guard=False, lift_arms=False)
    mixed = drape(body, shape, motion, garments, DrapeOptions(**base), models=models, defaults=MIXED)
    assert [g.method for g in mixed.garments] == [Method("learned", "learned"), Method("retarget", "none")]
    for g, draped in zip(garments, mixed.garments):
        m = MIXED.get(g.id)
        alone = drape(body, shape, motion, [g], DrapeOptions(fit=m.fit, dynamics=m.dynamics, **base), models=models)
        np.testing.assert_array_equal(draped.vertices, alone.garments[0].vertices)
    # an explicit option overrides the default for all: both garments run the learned model
    explicit = drape(body, shape, motion, garments, DrapeOptions(fit="learned", dynamics="learned", **base), models=models, defaults=MIXED)
    assert [g.method for g in explicit.garments] == [Method("learned", "learned")] * 2
    np.testing.assert_array_equal(explicit.garments[0].vertices, mixed.garments[0].vertices)
    assert np.abs(explicit.garments[1].vertices - mixed.garments[1].vertices).max() > 1e-3  # the T-shirt changed method


def test_pipeline_without_a_table_reads_the_shipped_file(scene):
    body, shape, motion, catalog, models = scene
    tshirt = catalog.get("tshirt")
    default = default_methods().get("tshirt")
    result = drape(body, shape, motion, [tshirt], DrapeOptions(guard=False, lift_arms=False), models=models)
    assert result.garments[0].method == default.method


def test_near_the_edge_of_the_range_the_default_blends_into_the_beyond_range_method():
    beyond = BeyondRange("learned-canonical", "none", "closest on the bodies split")
    table = DefaultMethods({"tshirt": DefaultMethod("canonical", "learned", beyond_range=beyond, **ENTRY),
                            "trousers": DefaultMethod("canonical", "learned", **ENTRY)})
    ids = ["tshirt", "trousers"]
    assert resolve_methods(ids, None, None, table, beyond=lambda g: 0.0) == [Method("canonical", "learned")] * 2
    assert resolve_methods(ids, None, None, table, beyond=lambda g: 1.0) == [Method("learned-canonical", "none"), Method("canonical", "none")]
    mixed = resolve_methods(ids, None, None, table, beyond=lambda g: 0.4)
    assert mixed == [Method("canonical", "learned", beyond=Method("learned-canonical", "none"), beyond_weight=0.4),
                     Method("canonical", "learned", beyond=Method("canonical", "none"), beyond_weight=0.4)]
    assert mixed[0].fits == ("canonical", "learned-canonical") and mixed[0].own == Method("canonical", "learned") and mixed[0].canonical
    # what a request names is never blended
    assert resolve_methods(ids, None, "learned", table, beyond=lambda g: 0.4) == [Method("canonical", "learned")] * 2


def test_an_outfit_runs_the_static_form_where_a_default_is_learned_canonical():
    """inference.defaults.OUTFIT_FIT: layered, a default's fit 'learned-canonical' (its own or its
    beyond-range method) runs the static canonical form; a request that names the fit keeps it."""
    beyond = BeyondRange("learned-canonical", "none", "closest on the bodies split")
    table = DefaultMethods({"croptop": DefaultMethod("learned-canonical", "none", **ENTRY),
                            "tshirt": DefaultMethod("canonical", "learned", beyond_range=beyond, **ENTRY),
                            "jacket": DefaultMethod("canonical", "none", **ENTRY)})
    far = lambda g: 1.0  # noqa: E731
    static, learned = Method("canonical", "none"), Method("learned-canonical", "none")
    assert resolve_methods(["croptop"], None, None, table, beyond=far) == [learned]
    assert resolve_methods(["croptop"], None, None, table, beyond=far, outfit=True) == [static]
    assert resolve_methods(["tshirt"], None, None, table, beyond=far) == [learned]
    assert resolve_methods(["croptop", "tshirt", "jacket"], None, None, table, beyond=far, outfit=True) == [static] * 3
    blended = resolve_methods(["tshirt", "jacket"], None, None, table, beyond=lambda g: 0.4, outfit=True)
    assert blended[0] == Method("canonical", "learned", beyond=static, beyond_weight=0.4)
    # within the range the learned canonical model runs, layered or not
    assert resolve_methods(["tshirt", "jacket"], None, None, table, beyond=lambda g: 0.0, outfit=True)[0] == Method("canonical", "learned")
    # named by the request: kept
    assert resolve_methods(["croptop", "tshirt"], "learned-canonical", "none", table, beyond=far, outfit=True) == [learned] * 2


def test_a_layered_drape_names_the_static_form_it_ran(scene):
    body, shape, motion, catalog, models = scene
    table = DefaultMethods({"croptop": DefaultMethod("learned-canonical", "none", **ENTRY), "jacket": DefaultMethod("canonical", "none", **ENTRY)})
    options = DrapeOptions(lift_arms=False)
    alone = drape(body, shape, motion, [catalog.get("croptop")], options, models=models, defaults=table)
    layered = drape(body, shape, motion, [catalog.get("croptop"), catalog.get("jacket")], options, models=models, defaults=table)
    assert alone.garments[0].method == Method("learned-canonical", "none")
    assert [g.method for g in layered.garments] == [Method("canonical", "none")] * 2
