"""Content-addressed result cache: identical requests are served from memory with the same
(weak) ETag; If-None-Match answers 304; any change of request, model version or garment default
method changes the key."""
from __future__ import annotations

import asyncio

import pytest
from fastapi.testclient import TestClient

from inference.defaults import DefaultMethod, DefaultMethods, default_methods
from service import cache as cache_module
from service.app import create_app
from service.cache import ResultCache, etag_matches, request_key
from service.config import Settings
from service.runtime import DrapeOutput
from service.schemas import DrapeRequest

BODY = {"motion": {"type": "clip", "clip": "walk", "duration_s": 0.2}, "garments": [{"id": "tshirt"}], "format": "npz",
        "options": {"include_body": False}}


@pytest.fixture(scope="module")
def cache_client(runtime):
    settings = Settings().model_copy(update={"worker_mode": "thread", "workers": 1, "jobs_backend": "off"})
    with TestClient(create_app(settings, runtime)) as c:
        yield c


def test_identical_requests_hit_the_cache(cache_client):
    a = cache_client.post("/v1/drape", json=BODY)
    b = cache_client.post("/v1/drape", json=BODY)
    assert a.status_code == b.status_code == 200
    assert a.headers["x-cache"] == "miss" and b.headers["x-cache"] == "hit"
    assert a.content == b.content and a.headers["etag"] == b.headers["etag"] and a.headers["etag"].startswith('W/"')
    other = cache_client.post("/v1/drape", json={**BODY, "options": {"include_body": False, "margin_m": 0.003}})
    assert other.headers["x-cache"] == "miss" and other.headers["etag"] != a.headers["etag"]


def test_if_none_match_answers_304(cache_client):
    etag = cache_client.post("/v1/drape", json=BODY).headers["etag"]
    r = cache_client.post("/v1/drape", json=BODY, headers={"If-None-Match": etag})
    assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag
    assert cache_client.post("/v1/drape", json=BODY, headers={"If-None-Match": 'W/"other"'}).status_code == 200


def test_key_covers_request_model_versions_and_default_methods(monkeypatch):
    r = DrapeRequest.model_validate(BODY)
    shipped = default_methods()
    key = request_key(r, "1", shipped, "a")
    assert key == request_key(DrapeRequest.model_validate(dict(reversed(list(BODY.items())))), "1", shipped, "a")  # canonical
    assert key != request_key(DrapeRequest.model_validate({**BODY, "format": "glb"}), "1", shipped, "a")
    # another default method for a garment (what omitted options run) is another key; another reason is not
    entries = {gid: DefaultMethod(**e) for gid, e in shipped.as_dict().items()}
    t = entries["tshirt"]
    other = DefaultMethod("retarget" if t.fit == "learned" else "learned", t.dynamics, t.reason, t.evidence)
    assert key != request_key(r, "1", DefaultMethods({**entries, "tshirt": other}), "a")
    reworded = DefaultMethod(t.fit, t.dynamics, t.reason + " (reworded)", t.evidence)
    assert key == request_key(r, "1", DefaultMethods({**entries, "tshirt": reworded}), "a")
    assert key != request_key(r, "1", shipped, "b")  # other asset contents
    monkeypatch.setitem(cache_module.MODEL_VERSIONS, "fit", "learned-v2")
    assert key != request_key(r, "1", shipped, "a")
    assert etag_matches(f'W/"{key}", "x"', key) and etag_matches(f'"{key}"', key) and not etag_matches("*", key)
    assert not etag_matches(None, key) and not etag_matches('"abc"', key)


def test_lru_is_bounded_by_bytes_and_coalesces():
    c = ResultCache(max_bytes=10)
    for i in range(4):
        c.put(str(i), DrapeOutput(payload=b"abcd", headers={}))
    assert c.size_bytes <= 10 and c.get("0") is None and c.get("3") is not None
    calls = []

    async def compute():
        calls.append(1)
        await asyncio.sleep(0.05)
        return DrapeOutput(payload=b"xy", headers={})

    async def main():
        return await asyncio.gather(*(c.get_or_compute("k", compute) for _ in range(3)))

    outs = asyncio.run(main())
    assert len(calls) == 1 and sorted(how for _, how in outs) == ["coalesced", "coalesced", "miss"]
