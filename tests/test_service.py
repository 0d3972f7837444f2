"""The HTTP API end to end: catalog routes, drape to glb (validated) and npz, problem+json errors."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from inference.metrics import layer_violations
from service.runtime import MODEL_VERSIONS
from tests.conftest import REPO_ROOT, validate_glb

WALK_TSHIRT = {
    "body": {"phenotypes": {"gender": 0.5, "age": 0.8, "muscle": 0.5, "weight": 0.5, "height": 0.5, "proportions": 0.5}},
    "motion": {"type": "clip", "clip": "walk", "duration_s": 1.0},
    "garments": [{"id": "tshirt"}],
}


def _problem(r, status, pointer_prefix=None):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["status"] == status and body["title"] and body["detail"]
    assert "Traceback" not in r.text
    if pointer_prefix is not None:
        pointers = [e["pointer"] for e in body.get("errors", [])]
        assert any(p.startswith(pointer_prefix) for p in pointers), pointers
    return body


def test_health_and_ready(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz").json()
    assert ready["status"] == "ready" and ready["garments"] >= 5 and ready["motions"] >= 7


def test_catalog_routes(client):
    garments = client.get("/v1/garments").json()["garments"]
    ids = {g["id"] for g in garments}
    assert {"tshirt", "longsleeve", "trousers", "dress", "jacket"} <= ids
    detail = client.get("/v1/garments/tshirt").json()
    assert detail["material"]["density_kg_m3"] == pytest.approx(426.0)
    # each garment's default method is the shipped file's entry, in the list and the detail
    shipped = json.loads((REPO_ROOT / "assets" / "models" / "defaults.json").read_text())["garments"]
    assert {g["id"]: g["default_method"] for g in garments} == shipped
    assert all(client.get(f"/v1/garments/{i}").json()["default_method"] == shipped[i] for i in ids)
    r = client.get("/v1/garments/tshirt/template.glb")
    assert r.status_code == 200 and r.content[:4] == b"glTF"
    _problem(client.get("/v1/garments/nope"), 404)


def test_body_model_and_motions(client):
    bm = client.get("/v1/body-model").json()
    assert len(bm["bones"]) == 31 and bm["bones"][0] == "Hips" and bm["parents"][0] == -1
    assert {p["name"] for p in bm["phenotypes"]} == {"gender", "age", "muscle", "weight", "height", "proportions"}
    motions = client.get("/v1/motions").json()
    ids = {m["id"] for m in motions["motions"]}
    assert {"walk", "run", "jump", "dance", "a_pose", "turntable", "01_01"} <= ids
    assert "mocap.cs.cmu.edu" in motions["acknowledgement"]


def test_drape_glb_passes_validator(client, tmp_path):
    r = client.post("/v1/drape", json={**WALK_TSHIRT, "format": "glb"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "model/gltf-binary"
    assert int(r.headers["x-frames"]) == 31
    path = tmp_path / "walk.glb"
    path.write_bytes(r.content)
    report = validate_glb(path)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]


def test_drape_npz_arrays(client):
    r = client.post("/v1/drape", json={**WALK_TSHIRT, "format": "npz"})
    assert r.status_code == 200, r.text
    data = np.load(io.BytesIO(r.content), allow_pickle=False)
    v = data["garment_0_vertices"]
    assert v.dtype == np.float32 and v.ndim == 3 and v.shape[0] == 31 and v.shape[2] == 3
    assert np.isfinite(v).all()
    assert data["garment_0_faces"].max() < v.shape[1]
    assert data["body_vertices"].shape[0] == 31
    assert float(data["fps"]) == 30.0
    import json

    meta = json.loads(str(data["metadata"]))
    assert [g["name"] for g in meta["garments"]] == ["tshirt"] and "metres" in meta["units"]
    # the garment moves over time (walk; frames 0 and 30 are near the same phase of the stride,
    # so any frame against the first)
    assert np.abs(v - v[0]).max() > 0.05


def test_drape_changes_with_shape(client):
    def verts(ph):
        r = client.post("/v1/drape", json={**WALK_TSHIRT, "body": {"phenotypes": ph}, "format": "npz", "options": {"include_body": False}})
        assert r.status_code == 200, r.text
        return np.load(io.BytesIO(r.content), allow_pickle=False)["garment_0_vertices"]

    small = verts({"weight": 0.0, "height": 0.0})
    large = verts({"weight": 1.0, "height": 1.0})
    assert small.shape == large.shape
    extent = lambda v: v[0].max(0) - v[0].min(0)  # noqa: E731
    assert (extent(large) > extent(small)).all()


def test_pose_sequence_and_bvh_motions(client):
    rot = np.zeros((5, 31, 3))
    rot[:, 10, 2] = np.linspace(0, 0.5, 5)  # LeftArm
    body = {"motion": {"type": "poses", "fps": 30, "rotations": rot.tolist(), "translation": np.zeros((5, 3)).tolist()},
            "garments": [{"id": "tshirt"}], "format": "npz"}
    r = client.post("/v1/drape", json=body)
    assert r.status_code == 200, r.text
    # a real CMU BVH (3ds Max joint names, metres), cut to its first 40 frames
    text = (REPO_ROOT / "training" / "sources" / "mocap" / "bvh" / "scaled_131_01.bvh").read_text()
    header, motion = text.split("MOTION", 1)
    lines = motion.strip().splitlines()
    frame_time = next(line for line in lines if line.startswith("Frame Time"))
    data = [line for line in lines if line and line[0] in "-0123456789"][:40]
    bvh = header + "MOTION\nFrames: 40\n" + frame_time + "\n" + "\n".join(data) + "\n"
    r = client.post("/v1/drape", json={"motion": {"type": "bvh", "bvh": bvh}, "garments": [{"id": "trousers"}], "format": "npz"})
    assert r.status_code == 200, r.text
    assert int(r.headers["x-frames"]) == 10  # 40 frames at 120 fps last 0.325 s -> 10 frames at 30 fps


@pytest.mark.parametrize(
    "patch, status, pointer",
    [
        ({"garments": [{"id": "nope"}]}, 422, "/garments/0"),
        ({"garments": []}, 422, "/garments"),
        ({"body": {"phenotypes": {"age": 0.5}}}, 422, "/body/phenotypes/age"),
        ({"body": {"phenotypes": {"weight": 1.5}}}, 422, "/body/phenotypes/weight"),
        ({"motion": {"type": "clip", "clip": "nope"}}, 422, "/motion"),
        ({"motion": {"type": "clip", "clip": "dance", "duration_s": 60}}, 422, "/motion"),
        ({"motion": {"type": "poses", "rotations": [[[0, 0, 0]] * 30], "translation": [[0, 0, 0]]}}, 422, "/motion"),
        ({"motion": {"type": "poses", "rotations": [[[0, 0, 0]] * 31] * 2, "translation": [[0, 0, 0]]}}, 422, "/motion/translation"),
        ({"motion": {"type": "bvh", "bvh": "HIERARCHY\nROOT Hips\n{\nOFFSET 0 0"}}, 422, "/motion"),
        ({"format": "obj"}, 422, "/format"),
        ({"extra": 1}, 422, "/extra"),
    ],
)
def test_bad_input_gets_problem_json(client, patch, status, pointer):
    _problem(client.post("/v1/drape", json={**WALK_TSHIRT, **patch}), status, pointer)


def test_nan_and_inf_are_rejected(client):
    body = '{"motion": {"type": "poses", "rotations": [' + ",".join(["[NaN, 0, 0]"] * 31).join("[]") + '], "translation": [[0, 0, Infinity]]}, "garments": [{"id": "tshirt"}]}'
    _problem(client.post("/v1/drape", content=body, headers={"content-type": "application/json"}), 422, "/motion")


def test_oversized_body_is_413(client, settings):
    big = b'{"x": "' + b"a" * (settings.max_request_bytes + 10) + b'"}'
    _problem(client.post("/v1/drape", content=big, headers={"content-type": "application/json"}), 413)


def test_malformed_json_is_400(client):
    _problem(client.post("/v1/drape", content=b"{not json", headers={"content-type": "application/json"}), 400)


def test_learned_models_are_selectable(client):
    def verts(options):
        r = client.post("/v1/drape", json={**WALK_TSHIRT, "format": "npz", "options": {"include_body": False, "guard": False, **options}})
        assert r.status_code == 200, r.text
        return np.load(io.BytesIO(r.content), allow_pickle=False)["garment_0_vertices"]

    r = client.post("/v1/drape", json={**WALK_TSHIRT, "format": "npz", "options": {"include_body": False, "fit": "learned", "dynamics": "learned"}})
    meta = json.loads(str(np.load(io.BytesIO(r.content), allow_pickle=False)["metadata"]))
    assert meta["model_versions"]["fit"]["tshirt"].startswith("snug-fit") and meta["model_versions"]["dynamics"]["tshirt"].startswith("snug-gru")
    base = verts({"fit": "retarget", "dynamics": "none"})
    learned = verts({"fit": "learned", "dynamics": "learned"})
    default = client.get("/v1/garments/tshirt").json()["default_method"]
    assert np.array_equal(verts({}), verts({"fit": default["fit"], "dynamics": default["dynamics"]}))  # omitted: the garment's default
    assert base.shape == learned.shape and np.isfinite(learned).all()
    assert np.abs(learned - base).max() > 1e-3  # the models change the garment
    # the wrinkle GRU output varies over time beyond the skinning (frames differ in unposed space)
    assert np.abs(np.diff(learned - base, axis=0)).max() > 1e-4


def test_arm_correction_is_on_by_default_and_optional(client):
    heavy = {**WALK_TSHIRT, "body": {"phenotypes": {"muscle": 1.0, "weight": 1.0, "height": 1.0, "proportions": 1.0, "gender": 1.0, "age": 1.0}},
             "format": "npz"}

    def run(options):
        r = client.post("/v1/drape", json={**heavy, "options": {"guard": False, **options}})
        assert r.status_code == 200, r.text
        z = np.load(io.BytesIO(r.content), allow_pickle=False)
        return z["body_vertices"], json.loads(str(z["metadata"]))["model_versions"]

    lifted, versions = run({})
    plain, versions_off = run({"lift_arms": False})
    assert versions["arms"].startswith("shoulder-lift") and versions_off["arms"] == "none"
    # the heavy body's arms move out of its torso; the returned body follows the corrected pose
    assert np.abs(lifted - plain).max() > 0.01


def test_guard_check_is_on_by_default_and_optional(client):
    heavy = {**WALK_TSHIRT, "body": {"phenotypes": {"muscle": 1.0, "weight": 1.0, "height": 1.0, "proportions": 1.0, "gender": 1.0, "age": 1.0}},
             "format": "npz"}

    def run(options):
        r = client.post("/v1/drape", json={**heavy, "options": options})
        assert r.status_code == 200, r.text
        z = np.load(io.BytesIO(r.content), allow_pickle=False)
        return z["garment_0_vertices"], json.loads(str(z["metadata"]))["model_versions"]

    retarget = {"fit": "retarget", "dynamics": "none"}  # a posed-space garment: the guard's pushes run (not a lone canonical one)
    checked, versions = run({**retarget, "guard_exact": False})
    plain, versions_off = run({**retarget, "guard_check": False, "guard_exact": False})
    assert versions["guard"] == "plane-push-v5" and versions_off["guard"] == "plane-push-v4"
    # the check moves the vertices the plane push left inside the body, and only those
    moved = np.linalg.norm(checked - plain, axis=-1) > 0
    assert 0 < moved.mean() < 0.01


def test_exact_repair_leaves_no_vertex_inside_the_body_by_default(client):
    from inference.metrics import inside_mask

    heavy = {**WALK_TSHIRT, "body": {"phenotypes": {"muscle": 1.0, "weight": 1.0, "height": 1.0, "proportions": 1.0, "gender": 1.0, "age": 1.0}},
             "garments": [{"id": "jacket"}], "format": "npz"}

    def run(options):
        r = client.post("/v1/drape", json={**heavy, "options": options})
        assert r.status_code == 200, r.text
        z = np.load(io.BytesIO(r.content), allow_pickle=False)
        inside = inside_mask(z["garment_0_vertices"], z["body_vertices"], z["body_faces"])
        return z["garment_0_vertices"], inside, json.loads(str(z["metadata"]))["model_versions"]

    # the retarget baseline: its raw drape does not change when the learned models are retrained
    # (the session-10 jacket left none inside after the guard alone on this body and clip)
    retarget = {"fit": "retarget", "dynamics": "none"}
    repaired, inside, versions = run(retarget)
    plain, inside_off, versions_off = run({**retarget, "guard_exact": False})
    assert versions["repair"] == "winding-repair-v5" and versions_off["repair"] == "none"
    assert inside_off.sum() > 0  # the guard alone leaves a few vertices in the body's folds
    assert inside.sum() == 0
    assert run({})[1].sum() == 0  # the garment's default method too
    moved = np.linalg.norm(repaired - plain, axis=-1) > 0
    assert moved.sum() >= inside_off.sum() and moved.mean() < 0.005  # those, and few others


def _glb_json(payload: bytes) -> dict:
    """The JSON chunk of a glb (12-byte header, then chunk length, type, data)."""
    length = int.from_bytes(payload[12:16], "little")
    return json.loads(payload[20:20 + length])


def test_drape_metadata_names_each_garments_method(client):
    """Omitted options run each garment's default; the metadata names what each garment ran."""
    body = {**WALK_TSHIRT, "garments": [{"id": "tshirt"}, {"id": "trousers"}], "motion": {"type": "clip", "clip": "walk", "duration_s": 0.2},
            "options": {"include_body": False, "guard": False}}
    defaults = {g: client.get(f"/v1/garments/{g}").json()["default_method"] for g in ("tshirt", "trousers")}
    versions = {"canonical": "diffused-canonical", "learned": "snug-", "retarget": "mhclo-retarget", "none": "none"}
    r = client.post("/v1/drape", json={**body, "format": "npz"})
    assert r.status_code == 200, r.text
    meta = json.loads(str(np.load(io.BytesIO(r.content), allow_pickle=False)["metadata"]))
    assert meta["options"]["fit"] is None and meta["options"]["dynamics"] is None  # the request as sent
    for g in meta["garments"]:
        d = defaults[g["name"]]
        assert (g["fit"], g["dynamics"]) == (d["fit"], d["dynamics"])
        assert meta["model_versions"]["fit"][g["name"]].startswith(versions[d["fit"]])
        dynamics = "canonical-vae-gru" if (d["fit"], d["dynamics"]) == ("canonical", "learned") else versions[d["dynamics"]]
        assert meta["model_versions"]["dynamics"][g["name"]].startswith(dynamics)
    # an explicit option is what every garment ran, in the glb too (each garment's node and asset.extras)
    r = client.post("/v1/drape", json={**body, "format": "glb", "options": {**body["options"], "fit": "retarget", "dynamics": "none"}})
    assert r.status_code == 200, r.text
    gltf = _glb_json(r.content)
    extras = [n["extras"] for n in gltf["nodes"] if "fit" in n.get("extras", {})]
    assert len(extras) == 2 and all((e["fit"], e["dynamics"]) == ("retarget", "none") for e in extras)
    assert gltf["asset"]["extras"]["model_versions"]["fit"] == {"tshirt": "mhclo-retarget", "trousers": "mhclo-retarget"}
    # the layer stage that ordered the outfit: none with collisions off, inference.layers' otherwise
    assert meta["model_versions"]["layers"] == "none" and gltf["asset"]["extras"]["model_versions"]["layers"] == "none"
    r = client.post("/v1/drape", json={**body, "format": "npz", "options": {"include_body": False}})
    assert r.status_code == 200, r.text
    meta = json.loads(str(np.load(io.BytesIO(r.content), allow_pickle=False)["metadata"]))
    assert meta["model_versions"]["layers"] == MODEL_VERSIONS["layers"]


def test_the_request_order_is_the_layer_order(client, runtime):
    """Garments are layered as listed, innermost first, whatever their catalog layers: a T-shirt
    listed before the trousers is tucked into them (its waist under theirs), listed after them it
    hangs over them; the response keeps the request's order."""
    tshirt, trousers = (runtime.catalog.get(g) for g in ("tshirt", "trousers"))
    assert tshirt.layer > trousers.layer  # the catalog's usual place: trousers inside
    drapes = {}
    for order in (("tshirt", "trousers"), ("trousers", "tshirt")):
        body = {**WALK_TSHIRT, "garments": [{"id": g} for g in order], "motion": {"type": "clip", "clip": "walk", "duration_s": 0.1},
                "format": "npz", "options": {"include_body": False}}
        r = client.post("/v1/drape", json=body)
        assert r.status_code == 200, r.text
        npz = np.load(io.BytesIO(r.content), allow_pickle=False)
        assert [g["name"] for g in json.loads(str(npz["metadata"]))["garments"]] == list(order)
        drapes[order] = {g: npz[f"garment_{i}_vertices"] for i, g in enumerate(order)}
    # where the two meet (T-shirt vertices within 2 cm of a trousers vertex): the T-shirt's on the
    # trousers' outer side (projecting onto them) when it hangs over them, few when tucked in
    outside = {}
    for order, v in drapes.items():
        beyond, _ = layer_violations(v["tshirt"], v["trousers"], trousers.faces)
        near = np.stack([cKDTree(o).query(t)[0] < 0.02 for t, o in zip(v["tshirt"], v["trousers"])])
        outside[order] = (int((beyond & near).sum()), int(near.sum()))
    (tucked, met_tucked), (over, met_over) = outside["tshirt", "trousers"], outside["trousers", "tshirt"]
    assert met_tucked > 500 and met_over > 500, outside
    assert over > 0.5 * met_over and tucked < 0.02 * met_tucked, outside


def _copy_defaults(tmp_path, **changes):
    data = json.loads((REPO_ROOT / "assets" / "models" / "defaults.json").read_text())
    for gid, entry in changes.items():
        data["garments"][gid].update(entry)
        if (data["garments"][gid]["fit"], data["garments"][gid]["dynamics"]) != ("canonical", "learned"):
            data["garments"][gid].pop("beyond_range", None)  # only beside a default with a body range
    path = tmp_path / "defaults.json"
    path.write_text(json.dumps(data))
    return path


def test_a_changed_defaults_file_changes_the_catalog_and_the_drape(tmp_path, settings, runtime, client):
    """The table alone decides: a copy where the T-shirt ships the retarget baseline and the
    trousers the learned model (the shipped file is never edited here) sets GET /v1/garments/tshirt,
    what a drape with the options omitted runs, and its metadata."""
    from fastapi.testclient import TestClient

    from inference.defaults import DefaultMethods
    from service.app import create_app
    from service.runtime import Runtime

    baseline = {"fit": "retarget", "dynamics": "none", "reason": "the baseline wins (test)", "evidence": "docs/evaluation.md"}
    path = _copy_defaults(tmp_path, tshirt=baseline, trousers={"fit": "learned", "dynamics": "learned"})
    thread = settings.model_copy(update={"worker_mode": "thread", "workers": 1, "jobs_backend": "off"})
    changed = Runtime(thread, runtime.body, runtime.catalog, runtime.clips, DefaultMethods.load(path, runtime.catalog.ids()))
    body = {"motion": {"type": "clip", "clip": "walk", "duration_s": 0.2}, "garments": [{"id": "tshirt"}, {"id": "trousers"}], "format": "npz"}

    def run(c, options):
        r = c.post("/v1/drape", json={**body, "options": {"include_body": False, "guard": False, **options}})
        assert r.status_code == 200, r.text
        z = np.load(io.BytesIO(r.content), allow_pickle=False)
        meta = json.loads(str(z["metadata"]))
        return {g["name"]: z[f"garment_{g['index']}_vertices"] for g in meta["garments"]}, meta, r.headers["etag"]

    with TestClient(create_app(thread, changed), raise_server_exceptions=False) as c:
        assert c.get("/v1/garments/tshirt").json()["default_method"] == baseline
        verts, meta, etag = run(c, {})
    assert {g["name"]: (g["fit"], g["dynamics"]) for g in meta["garments"]} == {"tshirt": ("retarget", "none"), "trousers": ("learned", "learned")}
    assert meta["model_versions"]["fit"] == {"tshirt": MODEL_VERSIONS["fit"], "trousers": MODEL_VERSIONS["learned_fit"]}
    # each garment equals an explicit drape with its method (guard off: the layers are independent),
    # to a micrometre: BLAS may round the last bit differently when the other garment's method
    # changes the shapes of the products (seen on some CPUs, 2.4e-7 m)
    np.testing.assert_allclose(verts["tshirt"], run(client, {"fit": "retarget", "dynamics": "none"})[0]["tshirt"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(verts["trousers"], run(client, {"fit": "learned", "dynamics": "learned"})[0]["trousers"], rtol=0, atol=1e-6)


def test_a_bad_defaults_file_stops_the_start_up(tmp_path, settings):
    """An assets folder whose defaults file names a garment the catalog lacks: the runtime (and
    so the app's start-up) fails with the file and the id in the message."""
    from inference.defaults import DefaultMethodsError
    from service.runtime import Runtime

    assets = tmp_path / "assets"
    (assets / "models").mkdir(parents=True)
    for name in ("body", "garments", "motions"):
        (assets / name).symlink_to(REPO_ROOT / "assets" / name)
    data = json.loads((REPO_ROOT / "assets" / "models" / "defaults.json").read_text())
    data["garments"]["cape"] = dict(data["garments"]["tshirt"])
    (assets / "models" / "defaults.json").write_text(json.dumps(data))
    with pytest.raises(DefaultMethodsError, match=r"defaults\.json: unknown garment ids \['cape'\]"):
        Runtime.load(settings.model_copy(update={"assets_dir": assets}))


def _amc_head(text: str, frames: int) -> str:
    """The AMC header and its first ``frames`` frames (a frame starts at a line holding its number)."""
    out, seen = [], 0
    for line in text.splitlines():
        if line.strip().isdigit():
            seen += 1
            if seen > frames:
                break
        out.append(line)
    return "\n".join(out) + "\n"


def test_drape_from_asf_amc(client):
    from inference.motion.resample import resampled_frame_count

    src = REPO_ROOT / "training" / "sources" / "mocap" / "cmu-asfamc" / "02"
    asf, amc = (src / "02.asf").read_text(), _amc_head((src / "02_01.amc").read_text(), 40)
    motion = {"type": "asf_amc", "asf": asf, "amc": amc}  # CMU: 120 fps, the ASF's own units
    r = client.post("/v1/drape", json={**WALK_TSHIRT, "motion": motion, "format": "npz", "options": {"include_body": False}})
    assert r.status_code == 200, r.text
    assert int(r.headers["x-frames"]) == resampled_frame_count(40, 120.0, 30.0)
    z = np.load(io.BytesIO(r.content), allow_pickle=False)
    assert np.isfinite(z["garment_0_vertices"]).all()
    bad = client.post("/v1/drape", json={**WALK_TSHIRT, "motion": {**motion, "amc": "1\nroot 0 0\n"}})
    _problem(bad, 422, "/motion")


def test_bundled_clips_are_in_place_by_default(client):
    def centroid_track(motion):
        r = client.post("/v1/drape", json={**WALK_TSHIRT, "motion": motion, "format": "npz", "options": {"include_body": True}})
        assert r.status_code == 200, r.text
        z = np.load(io.BytesIO(r.content), allow_pickle=False)
        return z["garment_0_vertices"].mean(axis=1), z["body_vertices"].mean(axis=1), json.loads(str(z["metadata"]))

    walk = {"type": "clip", "clip": "walk", "duration_s": 2.0}
    (g_in, b_in, meta_in), (g_out, b_out, meta_out) = centroid_track(walk), centroid_track({**walk, "in_place": False})
    travel = np.linalg.norm(g_out[-1, :2] - g_out[0, :2])
    assert travel > 1.0 and meta_out["in_place"] is False  # the walk covers metres
    assert np.abs(g_in[:, :2] - g_in[0, :2]).max() < 0.15 and meta_in["in_place"] is True  # on the spot: the sway only
    assert np.abs(b_in[:, :2] - b_in[0, :2]).max() < 0.15  # the body too
    np.testing.assert_allclose(g_in[:, 2], g_out[:, 2], atol=1e-5)  # the vertical is kept
    # the garment relative to the body is the same either way
    np.testing.assert_allclose(g_in - b_in, g_out - b_out, atol=1e-4)


def test_the_canonical_fit_is_selectable_and_named_in_the_metadata(client):
    r = client.post("/v1/drape", json={**WALK_TSHIRT, "format": "npz", "options": {"fit": "canonical", "dynamics": "none"}})
    assert r.status_code == 200, r.text
    z = np.load(io.BytesIO(r.content), allow_pickle=False)
    meta = json.loads(str(z["metadata"]))
    assert meta["model_versions"]["fit"]["tshirt"].startswith("diffused-canonical")
    assert meta["model_versions"]["guard"] == "none" and meta["model_versions"]["repair"].startswith("winding-repair")
    assert "body/diffused.npz" in meta["asset_files_sha256"]
    from inference.metrics import inside_mask

    assert not inside_mask(z["garment_0_vertices"], z["body_vertices"], z["body_faces"]).any()
    # the T-shirt ships a learned canonical model (regressor + decoder), named in the metadata ...
    r = client.post("/v1/drape", json={**WALK_TSHIRT, "format": "npz", "options": {"fit": "canonical", "dynamics": "learned"}})
    assert r.status_code == 200, r.text
    z = np.load(io.BytesIO(r.content), allow_pickle=False)
    meta = json.loads(str(z["metadata"]))
    assert meta["model_versions"]["dynamics"]["tshirt"].startswith("canonical-vae-gru")
    assert {"models/tshirt/canonical.json", "models/tshirt/canonical_decoder.onnx", "models/tshirt/canonical_regressor.onnx"} <= set(meta["asset_files_sha256"])
    assert not inside_mask(z["garment_0_vertices"], z["body_vertices"], z["body_faces"]).any()
    # ... the jacket does not: dynamics 'learned' is a 422 naming the field
    r = client.post("/v1/drape", json={**WALK_TSHIRT, "garments": [{"id": "jacket"}], "options": {"fit": "canonical", "dynamics": "learned"}})
    assert r.status_code == 422 and r.json()["errors"][0]["pointer"] == "/options/dynamics", r.text


def test_a_body_beyond_the_learned_models_range_runs_and_names_its_beyond_range_method(client):
    """GET /v1/garments/tshirt names the method a far body runs; a drape with the options omitted
    on such a body runs it, says so in model_versions and lists the files it read."""
    entry = client.get("/v1/garments/tshirt").json()["default_method"]
    assert (entry["fit"], entry["dynamics"]) == ("canonical", "learned") and entry["beyond_range"]["reason"]
    beyond = entry["beyond_range"]
    far = {"gender": 0.0, "age": 1.0, "muscle": 0.0, "weight": 0.0, "height": 1.0, "proportions": 1.0}  # 0.93 from its training bodies
    r = client.post("/v1/drape", json={**WALK_TSHIRT, "body": {"phenotypes": far}, "format": "npz",
                                       "motion": {"type": "clip", "clip": "walk", "duration_s": 0.2}})
    assert r.status_code == 200, r.text
    z = np.load(io.BytesIO(r.content), allow_pickle=False)
    meta = json.loads(str(z["metadata"]))
    g = meta["garments"][0]
    assert (g["fit"], g["dynamics"]) == (beyond["fit"], beyond["dynamics"])
    if beyond["fit"] == "learned-canonical":
        assert meta["model_versions"]["fit"]["tshirt"] == MODEL_VERSIONS["learned_canonical"]
        assert {"body/diffused.npz", "models/tshirt/fit.onnx"} <= set(meta["asset_files_sha256"])
        assert meta["model_versions"]["guard"] == "none" and meta["model_versions"]["repair"] == MODEL_VERSIONS["repair"]
    from inference.metrics import inside_mask

    assert not inside_mask(z["garment_0_vertices"], z["body_vertices"], z["body_faces"]).any()
    # at the edge of the range the two are blended, and the metadata says how
    from inference.body import PHENOTYPE_LABELS
    from inference.canonical import BODY_RANGE_BY_CATEGORY, CanonicalModels

    edge = CanonicalModels().train_phenotypes("tshirt")[0] + 0.95 * BODY_RANGE_BY_CATEGORY["top"] * np.array([0, 0, 0, -1, 0, 0], np.float32)
    r = client.post("/v1/drape", json={**WALK_TSHIRT, "body": {"phenotypes": dict(zip(PHENOTYPE_LABELS, edge.tolist()))}, "format": "npz",
                                       "motion": {"type": "clip", "clip": "walk", "duration_s": 0.2}})
    assert r.status_code == 200, r.text
    meta = json.loads(str(np.load(io.BytesIO(r.content), allow_pickle=False)["metadata"]))
    g = meta["garments"][0]
    assert (g["fit"], g["dynamics"]) == ("canonical", "learned") and 0.0 < g["beyond_range"]["weight"] < 0.5
    assert (g["beyond_range"]["fit"], g["beyond_range"]["dynamics"]) == (beyond["fit"], beyond["dynamics"])
    assert " + " in meta["model_versions"]["fit"]["tshirt"] and meta["model_versions"]["fit"]["tshirt"].startswith(MODEL_VERSIONS["canonical"])
