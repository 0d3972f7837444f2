"""Optional API-key auth (401 / 403 problem+json, constant-time match), CORS, request ids."""
from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.auth import key_matches
from service.config import Settings


@pytest.fixture(scope="module")
def auth_client(runtime, tmp_path_factory):
    keys_file = tmp_path_factory.mktemp("keys") / "keys.txt"
    keys_file.write_text("# one key per line\nfile-key\n")
    settings = Settings().model_copy(update={"worker_mode": "thread", "workers": 1, "jobs_backend": "off", "api_keys": "env-key, other",
                                             "api_keys_file": keys_file, "cors_origins": "https://shop.example"})
    with TestClient(create_app(settings, runtime), raise_server_exceptions=False) as c:
        yield c


def test_keys_from_env_and_file(auth_client):
    for key in ("env-key", "other", "file-key"):
        assert auth_client.get("/v1/garments", headers={"X-API-Key": key}).status_code == 200


def test_missing_key_is_401_wrong_key_is_403(auth_client):
    r = auth_client.get("/v1/garments")
    assert r.status_code == 401 and r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["title"] == "Unauthorized" and "X-API-Key" in r.headers["www-authenticate"]
    r = auth_client.post("/v1/drape", json={}, headers={"X-API-Key": "env-ke"})
    assert r.status_code == 403 and r.json()["status"] == 403
    assert "Traceback" not in r.text


def test_probes_and_metrics_stay_open(auth_client):
    for path in ("/healthz", "/readyz", "/metrics", "/openapi.json", "/docs", "/docs/assets/swagger-ui.css"):
        assert auth_client.get(path).status_code == 200, path


def test_key_matches_every_key_in_constant_time():
    import hashlib

    keys = [hashlib.sha256(k.encode()).digest() for k in ("a", "bb")]
    assert key_matches("bb", keys) and key_matches("a", keys)
    assert not key_matches("b", keys) and not key_matches("", keys) and not key_matches("\udcff", keys)


def test_cors_preflight_and_headers(auth_client):
    r = auth_client.options("/v1/drape", headers={"Origin": "https://shop.example", "Access-Control-Request-Method": "POST",
                                                  "Access-Control-Request-Headers": "content-type,x-api-key"})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://shop.example"
    r = auth_client.get("/v1/garments", headers={"Origin": "https://shop.example", "X-API-Key": "other"})
    assert r.headers["access-control-allow-origin"] == "https://shop.example" and "x-request-id" in r.headers["access-control-expose-headers"]
    r = auth_client.options("/v1/drape", headers={"Origin": "https://evil.example", "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in r.headers


def test_request_id_in_and_out(auth_client):
    r = auth_client.get("/healthz", headers={"X-Request-ID": "abc-123"})
    assert r.headers["x-request-id"] == "abc-123"
    r = auth_client.get("/healthz", headers={"X-Request-ID": "bad id\twith spaces"})
    assert r.headers["x-request-id"] != "bad id\twith spaces" and len(r.headers["x-request-id"]) == 32
    assert len(auth_client.get("/v1/garments").headers["x-request-id"]) == 32  # also on a 401
