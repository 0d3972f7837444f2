"""Audit D4 and D10: a drape is refused before its body is read when the pool would not take it;
large bodies are validated in another process with the same outcome as inline; a drape estimated
to outlast the deadline is sent to /v1/jobs with a 422 naming the motion."""
from __future__ import annotations

import asyncio
import gc
import json

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.parsing import KeyContext, RequestParser, validate

SMALL = {"motion": {"type": "clip", "clip": "a_pose", "duration_s": 0.1}, "garments": [{"id": "tshirt"}], "format": "npz",
         "options": {"include_body": False}}


def _poses(frames: int, bad_frame: int | None = None) -> bytes:
    rotations = [[[0.01 * (t % 7), 0.0, 0.0]] * 31 for t in range(frames)]
    if bad_frame is not None:
        rotations[bad_frame][4] = [0.0, "x", 0.0]
    return json.dumps({"motion": {"type": "poses", "fps": 30, "rotations": rotations, "translation": [[0, 0, 0]] * frames},
                       "garments": [{"id": "tshirt"}], "format": "npz"}).encode()


def test_refused_before_the_body_is_read(settings, runtime):
    """The request's body never arrives (receive blocks): the 503 comes anyway."""
    app = create_app(settings.model_copy(update={"worker_mode": "thread", "workers": 1, "jobs_backend": "off"}), runtime)
    with TestClient(app) as client:
        app.state.pool._accepting = False  # as when shutting down: admit() refuses

        async def call():
            sent, read = [], []

            async def receive():
                read.append(1)
                await asyncio.sleep(3600)

            async def send(message):
                sent.append(message)

            scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
                     "path": "/v1/drape", "raw_path": b"/v1/drape", "query_string": b"", "root_path": "",
                     "headers": [(b"content-type", b"application/json"), (b"content-length", b"100000")],
                     "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 80)}
            await asyncio.wait_for(app(scope, receive, send), 10)
            return sent, read

        sent, read = client.portal.call(call)
        assert sent[0]["status"] == 503 and read == []


def test_large_bodies_are_validated_in_a_process_with_the_inline_outcome(runtime):
    context = KeyContext("t", runtime.defaults, runtime.assets.combined)
    body, bad = _poses(600), _poses(600, bad_frame=123)
    assert len(body) > 256 * 1024
    parser = RequestParser(processes=1, inline_bytes=1024)
    parser.start()
    try:
        class _Request:  # what parse() reads of a starlette Request
            def __init__(self, data):
                self.data = data

            async def body(self):
                return self.data

        request, key = asyncio.run(parser.parse(_Request(body), context))
        inline_request, inline_key = validate(body, context)
        assert key == inline_key and request == inline_request and len(request.motion.rotations) == 600
        from fastapi.exceptions import RequestValidationError

        with pytest.raises(RequestValidationError) as err:
            asyncio.run(parser.parse(_Request(bad), context))
        assert [e["loc"][:5] for e in err.value.errors()] == [("body", "motion", "poses", "rotations", 123)]
        assert err.value.errors() == validate(bad, context)
    finally:
        parser.close()


def test_large_invalid_bodies_get_the_same_problem_over_http(client):
    bad = _poses(600, bad_frame=123)
    r = client.post("/v1/drape", content=bad, headers={"content-type": "application/json"})
    assert r.status_code == 422 and r.json()["errors"][0]["pointer"] == "/motion/rotations/123/4/1", r.text


def test_a_drape_estimated_past_the_deadline_is_sent_to_jobs(settings, runtime):
    deadline_s = 2.0
    s = settings.model_copy(update={"worker_mode": "thread", "workers": 1, "jobs_backend": "off", "request_timeout_s": deadline_s})
    app = create_app(s, runtime)
    # the short drapes must finish within the deadline: no collection of the whole test session's
    # heap (torch's, where training tests ran in this process) in the middle of one
    gc.collect()
    gc.freeze()
    try:
        with TestClient(app, raise_server_exceptions=False) as client:
            assert client.post("/v1/drape", json=SMALL).status_code == 200  # measures the cost per garment-frame
            per_gf = app.state.pool._gf_s
            assert 300 * per_gf > deadline_s, per_gf  # a 4-frame drape's cost per frame includes its fixed costs: ms, not us
            long = {**SMALL, "motion": {"type": "clip", "clip": "dance", "duration_s": 299 / 30.0}}  # 300 frames, the limit
            r = client.post("/v1/drape", json=long)
            assert r.status_code == 422 and r.json()["errors"][0]["pointer"] == "/motion" and "/v1/jobs" in r.json()["detail"], r.text
            assert client.post("/v1/drape", json=SMALL).status_code == 200  # short ones still pass
    finally:
        gc.unfreeze()
