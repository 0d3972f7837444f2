"""Garment catalog assets and the runtime binding (inference.garment)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from inference.body import ASSETS_DIR, NEUTRAL_PHENOTYPES, BodyModel
from inference.errors import InputShapeError, UnknownAssetError
from inference.garment import HM08_VERTEX_COUNT, GarmentCatalog, bind_garment
from inference.metrics import inside_mask, unsigned_distance

EXPECTED = {"tshirt": ("top", 1), "longsleeve": ("top", 1), "trousers": ("bottom", 0), "dress": ("dress", 1), "jacket": ("outer", 2),
            "crewtee": ("top", 1), "leggings": ("bottom", 0), "shorts": ("bottom", 0), "croptop": ("top", 1), "shirt": ("top", 1), "suittrousers": ("bottom", 0)}
EXTREMES = np.array([[0.0, 0.77, 0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]], np.float32)


@pytest.fixture(scope="module")
def catalog() -> GarmentCatalog:
    return GarmentCatalog.load()


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def neutral(body):
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    return shape, body.hm08_vertices(shape)


@pytest.fixture(scope="module", params=sorted(EXPECTED))
def garment(request, catalog):
    return catalog.get(request.param)


# ------------------------------------------------------------------------------ catalog
def test_catalog_ids_categories_layers(catalog):
    assert catalog.ids() == sorted(EXPECTED)
    for gid, (category, layer) in EXPECTED.items():
        g = catalog.get(gid)
        assert (g.id, g.category, g.layer) == (gid, category, layer)
    summaries = catalog.list()
    assert [s["id"] for s in summaries] == sorted(EXPECTED)
    assert all(s["licence"] == "CC0-1.0" and s["vertices"] > 0 for s in summaries)


def test_unknown_garment_raises(catalog):
    with pytest.raises(UnknownAssetError) as e:
        catalog.get("ballgown")
    assert e.value.field == "garment" and "ballgown" in str(e.value)
    assert "ballgown" not in catalog and "dress" in catalog


def test_material_in_si_units(garment):
    m = garment.material
    assert m["density_kg_m3"] == 426.0 and m["thickness_m"] == pytest.approx(0.47e-3)
    assert (m["lame_lambda_pa"], m["lame_mu_pa"]) == (4.44e4, 2.36e4)
    assert m["k_bend"] == pytest.approx(3.96e-5) and m["k_collision"] == 250.0
    if garment.category == "outer":
        assert 0.004 < m["collision_margin_m"] <= 0.015
    else:
        assert 0.002 <= m["collision_margin_m"] <= 0.004
    meta = json.loads((garment.directory / "garment.json").read_text())
    assert meta["vertices"] == garment.num_vertices and meta["build"]["command"].startswith("python -m training.assets.build_garments")


# ------------------------------------------------------------------------------ mesh
def test_arrays_dtypes_and_shapes(garment):
    V, F = garment.num_vertices, len(garment.faces)
    assert 2800 <= V <= 8000  # a few thousand: the shirt's source is already 2,822 (a 1-to-4 split would make 11k)
    for a in (garment.vertices, garment.rest_vertices, garment.uvs, garment.binding_weights, garment.binding_offsets,
              garment.scale_refs, garment.template_correction, garment.skin_weights):
        assert a.dtype == np.float32
    for a in (garment.faces, garment.edges, garment.face_uvs, garment.binding_indices):
        assert a.dtype == np.int32
    assert garment.face_uvs.shape == (F, 3) and garment.face_uvs.max() < len(garment.uvs)
    assert garment.skin_weights.shape == (V, 31)
    np.testing.assert_array_equal(garment.rest_vertices, garment.vertices)


def test_clean_mesh(garment):
    V = garment.num_vertices
    f = garment.faces
    assert np.array_equal(np.unique(f), np.arange(V)), "unreferenced vertices"
    assert not cKDTree(garment.vertices).query_pairs(1e-5), "duplicate positions"
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    np.testing.assert_array_equal(garment.edges, e)
    mesh = trimesh.Trimesh(garment.vertices, f, process=False)
    assert mesh.is_winding_consistent
    assert np.all(mesh.area_faces > 1e-7)  # no degenerate elements for the cloth model


def test_faces_point_away_from_body(garment, neutral):
    shape, _ = neutral
    mesh = trimesh.Trimesh(garment.vertices, garment.faces, process=False)
    centres = mesh.triangles_center[None].astype(np.float32)
    _, _, closest = unsigned_distance(centres, shape.rest_vertices, BodyModel.load().faces)
    away = np.einsum("fc,fc->f", mesh.face_normals, centres[0] - closest[0])
    assert np.sum(mesh.area_faces[away > 0]) > 0.9 * mesh.area


# ------------------------------------------------------------------------------ binding
def test_bind_hand_computed():
    """x = 0.25 B[5] + 0.75 B[7] + A (o * s), A: hm08 (x, y, z) -> anny (x, -z, y)."""
    rng = np.random.default_rng(0)
    H = rng.normal(size=(1, HM08_VERTEX_COUNT, 3)).astype(np.float32)
    H[0, 10], H[0, 11] = (0.0, 5.0, 5.0), (0.4, -3.0, 1.0)  # anny x distance 0.4
    H[0, 12], H[0, 13] = (2.0, 2.0, 0.0), (7.0, 9.0, 0.2)  # anny z distance 0.2 (hm08 y)
    H[0, 14], H[0, 15] = (1.0, 0.9, 3.0), (4.0, 0.0, 8.0)  # anny y distance 0.9 (hm08 z)
    refs = np.array([[10, 11, 4.0], [12, 13, 1.0], [14, 15, 3.0]], np.float32)  # scales 0.1, 0.2, 0.3
    idx = np.array([[5, 7]], np.int32)
    w = np.array([[0.25, 0.75]], np.float32)
    off = np.array([[1.0, 2.0, 3.0]], np.float32)  # hm08 offsets -> (0.1, 0.4, 0.9) -> anny (0.1, -0.9, 0.4)
    got = bind_garment(H, idx, w, off, refs)
    want = 0.25 * H[0, 5] + 0.75 * H[0, 7] + np.array([0.1, -0.9, 0.4])
    np.testing.assert_allclose(got[0, 0], want, atol=1e-6)
    with pytest.raises(InputShapeError):
        bind_garment(H[:, :100], idx, w, off, refs)


def test_bind_matches_makehuman_formula_in_hm08_frame(neutral):
    """Our anny-axes formula equals MakeHuman's proxy fitting done in hm08's own frame (Y-up, dm)."""
    from training.assets.garments_mesh import read_mhclo

    _, H = neutral
    mhclo = ASSETS_DIR.parent / "training/sources/makehuman/male_casualsuit02/male_casualsuit02.mhclo"
    idx, w, d, refs = read_mhclo(mhclo)
    hm = np.stack([H[0, :, 0], H[0, :, 2], -H[0, :, 1]], 1).astype(np.float64) * 10.0  # anny -> hm08
    scale = np.array([abs(hm[int(a), n] - hm[int(b), n]) / s for n, (a, b, s) in enumerate(refs)])
    x_hm = np.einsum("vk,vkc->vc", w, hm[idx]) + d * scale  # MakeHuman proxy.py getCoords
    want = np.stack([x_hm[:, 0], -x_hm[:, 2], x_hm[:, 1]], 1) / 10.0
    got = bind_garment(H, idx.astype(np.int32), w.astype(np.float32), d.astype(np.float32), refs.astype(np.float32))[0]
    np.testing.assert_allclose(got, want, atol=2e-6)


def test_bind_on_neutral_is_template_minus_correction(garment, neutral):
    _, H = neutral
    np.testing.assert_allclose(garment.bind(H)[0], garment.vertices - garment.template_correction, atol=1e-5)
    np.testing.assert_allclose(garment.retarget_fit(H)[0], garment.template, atol=1e-5)


def test_bind_batch_consistency(catalog, body):
    g = catalog.get("trousers")
    phen = np.stack([NEUTRAL_PHENOTYPES, *EXTREMES, [0.2, 0.9, 0.7, 0.3, 0.6, 0.4]]).astype(np.float32)
    H = body.hm08_vertices(body.shape(phen))
    batched = g.retarget_fit(H)
    for b in range(len(phen)):
        np.testing.assert_allclose(batched[b], g.retarget_fit(H[b : b + 1])[0], atol=1e-6)


def test_taller_body_longer_trousers(catalog, body):
    g = catalog.get("trousers")
    phen = np.repeat(NEUTRAL_PHENOTYPES[None], 2, 0)
    phen[:, 4] = (0.0, 1.0)  # height
    shape = body.shape(phen)
    fit = g.retarget_fit(body.hm08_vertices(shape))
    top, hem = fit[..., 2].max(1), fit[..., 2].min(1)
    assert top[1] - hem[1] > top[0] - hem[0] + 0.3
    # the hems stay at the ankles and the waistband just above the hip joints
    ankle = shape.bone_heads[:, body.bone_names.index("LeftFoot"), 2]
    hip = shape.bone_heads[:, body.bone_names.index("LeftUpLeg"), 2]
    assert np.all(np.abs(hem - ankle) < 0.03)
    assert np.all((top - hip > 0.03) & (top - hip < 0.15))


# ------------------------------------------------------------------------------ collision-free template
def test_template_collision_free_on_neutral(garment, neutral, body):
    shape, _ = neutral
    inside = inside_mask(garment.template[None], shape.rest_vertices, body.faces)
    assert inside.sum() == 0
    dist, _, _ = unsigned_distance(garment.template[None], shape.rest_vertices, body.faces)
    assert dist.min() >= garment.metadata["template_margin_m"] - 1e-4


# ------------------------------------------------------------------------------ skinning weights
def test_skin_weights_rows_sum_to_one(garment):
    w = garment.skin_weights
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-5)


def test_skin_weights_follow_body_regions(catalog, body):
    names = body.bone_names
    g = catalog.get("longsleeve")
    cuff = g.template[:, 0] > 0.45  # left sleeve end (+x is the body's left)
    assert np.all(g.skin_weights[cuff][:, [names.index("LeftForeArm"), names.index("LeftHand")]].sum(1) > 0.99)
    fingers = [names.index(n) for n in ("LThumb", "LeftFingerBase", "LeftHandFinger1", "RThumb", "LeftToeBase")]
    for gid in catalog.ids():
        assert np.all(catalog.get(gid).skin_weights[:, fingers] == 0), gid
    t = catalog.get("trousers")
    shin = (t.template[:, 0] < -0.05) & (t.template[:, 2] < -0.5)
    assert shin.sum() > 100
    assert np.all(t.skin_weights[shin][:, [names.index("RightLeg"), names.index("RightFoot")]].sum(1) > 0.9)


def test_dress_skirt_weights_are_smooth(catalog, body, neutral):
    """Closest-triangle weights tear the skirt between the legs; the dress's are diffused."""
    from training.assets.garments_fit import fold_into_parents, project_skin_weights

    shape, _ = neutral
    names = body.bone_names
    g = catalog.get("dress")
    v, e, w = g.template, g.edges, g.skin_weights
    skirt = v[:, 2] < 0.09  # fully diffused below the skirt top minus the blend ramp
    in_skirt = skirt[e[:, 0]] & skirt[e[:, 1]]
    jump = np.abs(w[e[:, 0]] - w[e[:, 1]]).sum(1)[in_skirt]
    raw = project_skin_weights(v.astype(np.float64), shape.rest_vertices[0].astype(np.float64), body.faces.astype(np.int64), body.dense_weights)
    raw_jump = np.abs(raw[e[:, 0]] - raw[e[:, 1]]).sum(1)[in_skirt]
    assert raw_jump.max() > 1.5  # the tear the smoothing removes
    assert jump.max() < 0.4 and np.percentile(jump, 99) < 0.25
    # front centre below the crotch: both thighs pull on the cloth
    front = (np.abs(v[:, 0]) < 0.02) & (v[:, 1] < 0) & (v[:, 2] < 0.0)
    legs = w[front][:, [names.index("LeftUpLeg"), names.index("RightUpLeg")]]
    assert front.sum() > 5 and np.all(legs > 0.3)
    # the blouse above keeps the projected weights of the body surface it faces (fingers folded,
    # tiny weights dropped)
    top = v[:, 2] > 0.3
    fold = [names.index(n) for n in ("LThumb", "LeftFingerBase", "LeftHandFinger1", "RThumb", "RightFingerBase",
                                     "RightHandFinger1", "LeftToeBase", "RightToeBase")]
    from inference.mesh import vertex_normals
    from training.assets.build_garments import SKIN_PROBE_DEPTH_M

    probe = v - SKIN_PROBE_DEPTH_M * vertex_normals(v[None], g.faces)[0]  # the faced body surface
    faced = project_skin_weights(probe.astype(np.float64), shape.rest_vertices[0].astype(np.float64), body.faces.astype(np.int64), body.dense_weights)
    ref = fold_into_parents(faced[top], body.parents, np.array(fold))
    ref = np.where(ref < 1e-3, 0.0, ref)
    np.testing.assert_allclose(w[top], ref / ref.sum(1, keepdims=True), atol=1e-5)


# ------------------------------------------------------------------------------ retargeting on extreme shapes
def test_retarget_extremes_mostly_outside(catalog, body):
    """Retargeting keeps the garment on the body at the phenotype extremes (residue: runtime guard)."""
    shape = body.shape(EXTREMES)
    H = body.hm08_vertices(shape)
    for gid in catalog.ids():
        g = catalog.get(gid)
        inside = inside_mask(g.retarget_fit(H), shape.rest_vertices, body.faces)
        assert inside.mean() < 0.05, gid
        assert inside.mean() < inside_mask(g.bind(H), shape.rest_vertices, body.faces).mean() + 1e-9, gid


# ------------------------------------------------------------------------------ glb
def glb_json(path) -> str:
    data = path.read_bytes()
    (length,) = np.frombuffer(data[12:16], np.uint32)
    return data[20:20 + int(length)].decode()


def test_template_glb(garment):
    """The template on the floor (lifted by the neutral body's sole height), in its own colour, not metal."""
    scene = trimesh.load(garment.directory / "template.glb", force="scene")
    (mesh,) = scene.geometry.values()
    assert mesh.visual.uv is not None and len(mesh.visual.uv) == len(mesh.vertices)
    assert len(mesh.faces) == len(garment.faces)
    floor_z = float(BodyModel.load().shape(NEUTRAL_PHENOTYPES[None]).rest_vertices[0, :, 2].min())
    yup = np.stack([garment.vertices[:, 0], garment.vertices[:, 2] - floor_z, -garment.vertices[:, 1]], 1)
    np.testing.assert_allclose(scene.bounds, np.stack([yup.min(0), yup.max(0)]), atol=1e-5)
    gltf = json.loads(glb_json(garment.directory / "template.glb"))
    (material,) = gltf["materials"]
    pbr = material["pbrMetallicRoughness"]
    assert pbr["metallicFactor"] == 0.0 and 0.5 <= pbr["roughnessFactor"] <= 1.0
    np.testing.assert_allclose(pbr["baseColorFactor"][:3], garment.appearance["base_color"])
    assert "NORMAL" in gltf["meshes"][0]["primitives"][0]["attributes"]


def test_template_glb_passes_khronos_validator(catalog):
    from tests.conftest import validate_glb

    report = validate_glb(catalog.get("dress").directory / "template.glb")
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0
