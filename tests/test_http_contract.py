"""The HTTP contract where the framework's defaults differ from the RFCs (audit D6-D9): field
pointers into the request document (RFC 6901), 400 for unparseable JSON, 415 for a body that
is not JSON, 413 for a streamed body past the limit, HEAD on GET routes, 412 for
``If-None-Match: *`` on POST, and a contract whose limits are the server's."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest

from service.errors import field_of

CLIP = {"motion": {"type": "clip", "clip": "a_pose", "duration_s": 0.03}, "garments": [{"id": "tshirt"}], "format": "npz",
        "options": {"include_body": False}}


def _errors(r, status):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    return r.json().get("errors", [])


def test_pointers_are_rfc6901_pointers_into_the_request(client):
    bad_weight = {**CLIP, "body": {"phenotypes": {"weight": 7.0}}}
    assert [e["pointer"] for e in _errors(client.post("/v1/drape", json=bad_weight), 422)] == ["/body/phenotypes/weight"]
    bad_start = {**CLIP, "motion": {**CLIP["motion"], "start_s": -1.0}}
    assert [e["pointer"] for e in _errors(client.post("/v1/drape", json=bad_start), 422)] == ["/motion/start_s"]
    unknown_clip = {**CLIP, "motion": {"type": "clip", "clip": "nope"}}
    assert [e["pointer"] for e in _errors(client.post("/v1/drape", json=unknown_clip), 422)] == ["/motion/clip"]
    unknown_garment = {**CLIP, "garments": [{"id": "tshirt"}, {"id": "nope"}]}
    assert [e["pointer"] for e in _errors(client.post("/v1/drape", json=unknown_garment), 422)] == ["/garments/1/id"]
    job = _errors(client.get("/v1/jobs/not-an-id"), 422)
    assert job[0]["parameter"] == "job_id" and job[0]["in"] == "path" and "pointer" not in job[0]


def test_pointer_escapes_and_tags():
    assert field_of(("body", "motion", "clip", "clip")) == {"pointer": "/motion/clip"}
    assert field_of(("body", "motion")) == {"pointer": "/motion"}
    assert field_of(("body", "a/b", "m~n")) == {"pointer": "/a~1b/m~0n"}
    assert field_of(("body",)) == {"pointer": ""}


def test_the_motion_type_is_required_and_documented_so(client):
    untyped = {**CLIP, "motion": {"clip": "a_pose"}}
    assert [e["pointer"] for e in _errors(client.post("/v1/drape", json=untyped), 422)] == ["/motion"]
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    for name in ("ClipMotion", "PoseMotion", "BvhMotion"):
        assert "type" in schemas[name]["required"], name


def test_contract_limits_are_the_servers(client, settings):
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    assert schemas["DrapeRequest"]["properties"]["garments"]["maxItems"] == settings.max_garments
    assert schemas["PoseMotion"]["properties"]["rotations"]["maxItems"] == settings.max_source_frames
    too_many = {**CLIP, "garments": [{"id": g} for g in ("tshirt", "longsleeve", "trousers", "dress", "jacket")][: settings.max_garments + 1]}
    assert len(too_many["garments"]) > settings.max_garments
    assert [e["pointer"] for e in _errors(client.post("/v1/drape", json=too_many), 422)] == ["/garments"]


def test_unparseable_json_is_400_and_a_non_json_body_415(client):
    r = client.post("/v1/drape", content=b'{"motion": ', headers={"content-type": "application/json"})
    assert r.status_code == 400 and r.json()["title"] == "Malformed JSON", r.text
    for content_type in ("text/plain", "application/x-www-form-urlencoded", None):
        headers = {"content-type": content_type} if content_type else {}
        r = client.post("/v1/drape", content=json.dumps(CLIP).encode(), headers=headers)
        assert r.status_code == 415 and r.headers["accept-post"] == "application/json", (content_type, r.text)
    r = client.post("/v1/jobs", content=b"x", headers={"content-type": "text/csv"})
    assert r.status_code == 415
    r = client.post("/v1/drape", content=json.dumps(CLIP).encode(), headers={"content-type": "application/json; charset=utf-8"})
    assert r.status_code == 200, r.text


def test_a_streamed_body_past_the_limit_is_413(client, settings):
    def chunks():
        piece = b" " * 65536
        for _ in range(settings.max_request_bytes // len(piece) + 2):
            yield piece

    r = client.post("/v1/drape", content=chunks(), headers={"content-type": "application/json"})
    assert "content-length" not in {k.lower() for k in r.request.headers}  # chunked: the size is only known by reading
    assert r.status_code == 413 and r.json()["title"] == "Request too large", r.text


def test_head_answers_the_gets_headers_without_a_body(client):
    for path in ("/v1/garments", "/v1/garments/tshirt/template.glb", "/healthz"):
        for coding in ("identity", "gzip"):
            get, head = client.get(path, headers={"accept-encoding": coding}), client.head(path, headers={"accept-encoding": coding})
            assert head.status_code == get.status_code == 200, (path, head.text)
            assert head.content == b"" and head.headers["content-type"] == get.headers["content-type"]
            for name in ("content-length", "content-encoding", "etag"):
                assert head.headers.get(name) == get.headers.get(name), (path, coding, name)
            if coding == "identity":
                assert head.headers.get("content-length") == str(len(get.content))
    assert client.head("/v1/garments/nope").status_code == 404


def test_if_none_match_star_on_post_is_412_after_validation(client):
    r = client.post("/v1/drape", json=CLIP, headers={"if-none-match": "*"})
    assert r.status_code == 412, r.text
    invalid = {**CLIP, "garments": []}
    assert client.post("/v1/drape", json=invalid, headers={"if-none-match": "*"}).status_code == 422
    first = client.post("/v1/drape", json=CLIP)
    assert first.status_code == 200
    assert client.post("/v1/drape", json=CLIP, headers={"if-none-match": first.headers["etag"]}).status_code == 304


def test_docs_are_served_without_a_cdn(client):
    page = client.get("/docs")
    assert page.status_code == 200 and "/docs/assets/swagger-ui-bundle.js" in page.text
    assert "cdn" not in page.text.lower() and "http://" not in page.text and "https://" not in page.text.replace("https://swagger.io", "")
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css"):
        r = client.get(f"/docs/assets/{asset}")
        assert r.status_code == 200 and len(r.content) > 10_000


def test_catalog_routes_carry_an_etag_and_answer_304(client):
    for path in ("/v1/garments", "/v1/garments/tshirt", "/v1/garments/tshirt/template.glb", "/v1/motions", "/v1/body-model"):
        r = client.get(path)
        assert r.status_code == 200 and r.headers["etag"].startswith('"') and "max-age" in r.headers["cache-control"], path
        again = client.get(path, headers={"if-none-match": r.headers["etag"]})
        assert again.status_code == 304 and again.content == b"" and again.headers["etag"] == r.headers["etag"], path
        assert client.get(path, headers={"if-none-match": '"other"'}).status_code == 200
    tags = {client.get(p).headers["etag"] for p in ("/v1/garments/tshirt", "/v1/garments/dress")}
    assert len(tags) == 2  # per path
    assert "etag" not in client.get("/v1/garments/nope").headers  # errors are not tagged


def test_binary_answers_are_described_as_binary(client):
    paths = client.get("/openapi.json").json()["paths"]
    answers = [paths["/v1/drape"]["post"]["responses"]["200"]["content"], paths["/v1/jobs/{job_id}/result"]["get"]["responses"]["200"]["content"],
               paths["/v1/garments/{garment_id}/template.glb"]["get"]["responses"]["200"]["content"]]
    for content in answers:
        for media in content.values():
            assert media["schema"] == {"type": "string", "format": "binary"}


def test_accept_selects_the_format_and_refuses_what_it_cannot_serve(client):
    from service.parsing import accepted_formats

    assert accepted_formats(None) is None and accepted_formats("*/*") is None
    assert accepted_formats("application/x-npz") == ("npz",)
    assert accepted_formats("model/gltf-binary;q=0.5, application/x-npz") == ("npz", "glb")
    assert accepted_formats("text/html, */*;q=0.8") == ("glb", "npz")
    assert accepted_formats("model/*") == ("glb",) and accepted_formats("application/json") == ()
    assert accepted_formats("application/x-npz;q=0, model/gltf-binary") == ("glb",)

    unformatted = {k: v for k, v in CLIP.items() if k != "format"}
    npz = client.post("/v1/drape", json=unformatted, headers={"accept": "application/x-npz"})
    assert npz.status_code == 200 and npz.headers["content-type"] == "application/x-npz"
    assert "Accept" in [v.strip() for v in npz.headers["vary"].split(",")]  # and Accept-Encoding (gzip)
    glb = client.post("/v1/drape", json=unformatted, headers={"accept": "model/gltf-binary"})
    assert glb.status_code == 200 and glb.headers["content-type"] == "model/gltf-binary" and glb.content[:4] == b"glTF"
    assert glb.headers["etag"] != npz.headers["etag"]
    assert client.post("/v1/drape", json=unformatted).headers["content-type"] == "model/gltf-binary"  # no Accept: the default
    refused = client.post("/v1/drape", json=CLIP, headers={"accept": "model/gltf-binary"})  # the body says npz
    assert refused.status_code == 406 and "npz" in refused.json()["detail"], refused.text
    assert client.post("/v1/drape", json=unformatted, headers={"accept": "application/json"}).status_code == 406


def test_collisions_is_one_choice_and_the_old_flags_map_to_it():
    from inference.options import DrapeOptions

    assert DrapeOptions().collisions == "exact"
    assert DrapeOptions.model_validate({"guard": False}).collisions == "off"
    assert DrapeOptions.model_validate({"guard_exact": False}).collisions == "check"
    assert DrapeOptions.model_validate({"guard_exact": False, "guard_check": False}).collisions == "push"
    o = DrapeOptions(collisions="check")
    assert (o.guard, o.guard_check, o.guard_exact) == (True, True, False)
    assert o.replace(guard=False).collisions == "off" and o.replace(guard_exact=True).collisions == "exact"
    with pytest.raises(ValueError):
        DrapeOptions.model_validate({"collisions": "exact", "guard": False})  # contradictory


def test_the_contract_names_collisions_not_the_flags(client):
    schema = client.get("/openapi.json").json()["components"]["schemas"]["DrapeOptions"]["properties"]
    assert schema["collisions"]["enum"] == ["off", "push", "check", "exact"] and schema["collisions"]["default"] == "exact"
    assert not {"guard", "guard_check", "guard_exact"} & set(schema)
    r = client.post("/v1/drape", json={**CLIP, "options": {"include_body": False, "collisions": "off"}})
    assert r.status_code == 200
    meta = json.loads(str(np.load(io.BytesIO(r.content), allow_pickle=False)["metadata"]))
    assert meta["options"]["collisions"] == "off" and meta["model_versions"]["guard"] == "none"


def _raw(client, body: dict, accept_encoding: str):
    """The answer's bytes as sent (httpx would decode a gzip body) and its headers."""
    with client.stream("POST", "/v1/drape", json=body, headers={"accept": "model/gltf-binary", "accept-encoding": accept_encoding}) as r:
        assert r.status_code == 200, r.read()
        return b"".join(r.iter_raw()), r.headers


def test_a_glb_drape_is_gzip_encoded_when_the_client_accepts_it(client, tmp_path):
    import gzip
    import shutil

    import pygltflib

    from tests.conftest import REPO_ROOT, validate_glb

    body = {"motion": {"type": "clip", "clip": "walk", "duration_s": 0.5}, "garments": [{"id": "tshirt"}], "format": "glb"}
    zipped, zh = _raw(client, body, "gzip")
    plain, ph = _raw(client, body, "identity")
    assert zh["content-encoding"] == "gzip" and int(zh["content-length"]) == len(zipped)
    assert "content-encoding" not in ph and int(ph["content-length"]) == len(plain) and plain[:4] == b"glTF"
    assert gzip.decompress(zipped) == plain and len(zipped) < 0.9 * len(plain)
    gltf = pygltflib.GLTF2.load_from_bytes(gzip.decompress(zipped))
    assert gltf.asset.extras["frames"] == int(zh["x-frames"]) and len(gltf.animations) == 1
    if shutil.which("node") and (REPO_ROOT / "node_modules" / "gltf-validator").is_dir():
        (tmp_path / "gunzipped.glb").write_bytes(gzip.decompress(zipped))
        assert validate_glb(tmp_path / "gunzipped.glb")["issues"]["numErrors"] == 0
    # the drape's tag is weak (equivalent content, whatever the coding): the same for both, and it revalidates either
    assert zh["etag"] == ph["etag"] and zh["etag"].startswith("W/")
    assert "Accept-Encoding" in zh["vary"] and "Accept" in [v.strip() for v in zh["vary"].split(",")]
    again = client.post("/v1/drape", json=body, headers={"accept-encoding": "gzip", "if-none-match": zh["etag"]})
    assert again.status_code == 304


def test_drape_answers_are_gzipped_to_the_same_bytes_every_time():
    """``gzip_mesh`` (ISA-L): a gzip stream any client decodes (Python's gzip and zlib), the same
    bytes for the same answer (its ETag names them), within a few % of zlib level 1's size on mesh
    data (float vertices, int faces)."""
    import gzip
    import zlib

    import numpy as np

    from service.http_rules import gzip_mesh

    rng = np.random.default_rng(0)
    verts = (rng.normal(0.0, 0.3, (30, 5000, 3))).astype(np.float32).tobytes()
    faces = np.sort(rng.integers(0, 5000, (10000, 3)), axis=0).astype(np.int32).tobytes()
    payload = verts + faces
    zipped = gzip_mesh(payload)
    assert zipped[:2] == b"\x1f\x8b" and gzip.decompress(zipped) == payload
    assert gzip_mesh(payload) == zipped
    level1 = gzip.compress(payload, 1, mtime=0)
    assert len(zipped) < 1.05 * len(level1) and len(zipped) < len(payload)
    assert len(zlib.decompress(zipped, 16 + zlib.MAX_WBITS)) == len(payload)


def test_catalog_tags_differ_per_coding_and_revalidate(client):
    plain = client.get("/v1/garments", headers={"accept-encoding": "identity"})
    zipped = client.get("/v1/garments", headers={"accept-encoding": "gzip"})
    assert "content-encoding" not in plain.headers and zipped.headers["content-encoding"] == "gzip"
    assert zipped.headers["etag"] == plain.headers["etag"][:-1] + '-gzip"' and zipped.json() == plain.json()
    for coding, tag in (("identity", plain.headers["etag"]), ("gzip", zipped.headers["etag"])):
        again = client.get("/v1/garments", headers={"accept-encoding": coding, "if-none-match": tag})
        assert again.status_code == 304 and again.headers["etag"] == tag, coding
    small = client.get("/healthz", headers={"accept-encoding": "gzip"})
    assert "content-encoding" not in small.headers  # under 1 KB: not worth it
