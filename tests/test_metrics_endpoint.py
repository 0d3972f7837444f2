"""GET /metrics (Prometheus), /readyz reflecting worker health, structured JSON logs."""
from __future__ import annotations

import json
import logging

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from service.app import create_app
from service.config import Settings
from service.logs import JsonFormatter, request_id_var
from service.runtime import MODEL_VERSIONS


@pytest.fixture(scope="module")
def metrics_client(runtime, tmp_path_factory):
    settings = Settings().model_copy(update={"worker_mode": "thread", "workers": 1, "jobs_dir": tmp_path_factory.mktemp("jobs"), "cache_max_bytes": 0})
    with TestClient(create_app(settings, runtime), raise_server_exceptions=False) as c:
        yield c


def _samples(client) -> dict:
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    out = {}
    for family in text_string_to_metric_families(r.text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def test_metrics_cover_requests_latency_queue_batches_inference_jobs(metrics_client):
    body = {"motion": {"type": "clip", "clip": "walk", "duration_s": 0.2}, "garments": [{"id": "tshirt"}], "format": "npz",
            "options": {"fit": "learned", "dynamics": "learned"}}
    assert metrics_client.post("/v1/drape", json=body).status_code == 200
    metrics_client.get("/v1/garments/nope")
    m = _samples(metrics_client)
    assert m[("tryon_http_requests_total", (("method", "POST"), ("route", "/v1/drape"), ("status", "200")))] >= 1
    assert m[("tryon_http_requests_total", (("method", "GET"), ("route", "/v1/garments/{garment_id}"), ("status", "404")))] >= 1
    assert m[("tryon_http_request_duration_seconds_count", (("method", "POST"), ("route", "/v1/drape")))] >= 1
    assert ("tryon_queue_depth", ()) in m
    assert m[("tryon_batch_size_count", ())] >= 1
    assert m[("tryon_inference_ms_count", (("model", MODEL_VERSIONS["guard"]), ("stage", "guard")))] >= 1
    # a request for the learned models: the stage label names them
    assert m[("tryon_inference_ms_count", (("model", MODEL_VERSIONS["learned_fit"]), ("stage", "fit")))] >= 1
    assert m[("tryon_inference_ms_count", (("model", MODEL_VERSIONS["learned_dynamics"]), ("stage", "dynamics")))] >= 1
    assert ("tryon_inference_ms_count", (("model", MODEL_VERSIONS["fit"]), ("stage", "fit"))) not in m
    assert {("tryon_jobs", (("state", s),)) for s in ("queued", "running", "succeeded", "failed", "cancelled")} <= set(m)
    assert m[("tryon_workers_alive", ())] == 1


def test_readyz_reports_workers(metrics_client):
    r = metrics_client.get("/readyz").json()
    assert r["status"] == "ready" and r["workers"][0]["alive"] and r["jobs_backend"] == "sqlite"


def test_readyz_is_503_when_not_serving(runtime):
    app = create_app(Settings().model_copy(update={"jobs_backend": "off"}), runtime)
    with TestClient(app, raise_server_exceptions=False) as c:  # lifespan not entered: no pool
        pass
    c = TestClient(app, raise_server_exceptions=False)
    r = c.get("/readyz")
    assert r.status_code == 503 and r.headers["retry-after"] == "1"


def test_json_log_lines_carry_the_request_id():
    token = request_id_var.set("rid-42")
    try:
        record = logging.LogRecord("service.x", logging.INFO, __file__, 1, "hello %s", ("world",), None)
        line = json.loads(JsonFormatter().format(record))
    finally:
        request_id_var.reset(token)
    assert line["message"] == "hello world" and line["request_id"] == "rid-42" and line["level"] == "info"
