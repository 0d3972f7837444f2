"""Chaos: kill an inference worker during a request; kill and restart the whole service during
a job. Nothing accepted is lost and nothing hangs."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.config import Settings
from tests.conftest import REPO_ROOT

pytestmark = pytest.mark.timeout(240)

SLOW = {"motion": {"type": "clip", "clip": "dance", "duration_s": 3.0}, "garments": [{"id": "tshirt"}], "format": "npz",
        "options": {"include_body": False}}  # ~1 s of guard work


def _busy_worker_pid(client, timeout_s=20.0) -> int:
    pool = client.app.state.pool
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if pool._busy:
            return pool.workers[0].pid
        time.sleep(0.01)
    raise AssertionError("the worker never started the request")


@pytest.fixture
def process_client(tmp_path):
    settings = Settings().model_copy(update={"worker_mode": "process", "workers": 1, "jobs_backend": "off", "cache_max_bytes": 0, "max_wait_ms": 0.0})
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        yield c


def test_killed_worker_is_replaced_and_its_request_retried(process_client):
    c = process_client
    result = {}
    t = threading.Thread(target=lambda: result.update(r=c.post("/v1/drape", json=SLOW)))
    t.start()
    pid = _busy_worker_pid(c)
    time.sleep(0.2)
    os.kill(pid, signal.SIGKILL)
    t.join(120)
    assert not t.is_alive()
    r = result["r"]
    assert r.status_code == 200, r.text  # retried once on the fresh worker
    assert int(r.headers["x-frames"]) == 91
    pool = c.app.state.pool
    assert pool.workers[0].pid != pid and pool.workers[0].alive()
    assert c.get("/readyz").status_code == 200
    assert "tryon_worker_restarts_total 1.0" in c.get("/metrics").text


def test_request_that_kills_two_workers_gets_a_500_problem(process_client):
    c = process_client
    result = {}
    t = threading.Thread(target=lambda: result.update(r=c.post("/v1/drape", json=SLOW)))
    t.start()
    first = _busy_worker_pid(c)
    time.sleep(0.1)
    os.kill(first, signal.SIGKILL)
    t0 = time.monotonic()
    while c.app.state.pool.workers[0].pid == first or not c.app.state.pool._busy:
        assert time.monotonic() - t0 < 60
        time.sleep(0.01)
    time.sleep(0.1)
    os.kill(c.app.state.pool.workers[0].pid, signal.SIGKILL)
    t.join(120)
    r = result["r"]
    assert r.status_code == 500 and r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["title"] == "Worker failed" and "Traceback" not in r.text
    assert c.post("/v1/drape", json={**SLOW, "motion": {"type": "clip", "clip": "walk", "duration_s": 0.1}}).status_code == 200


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serve(port: int, jobs_dir) -> subprocess.Popen:
    env = {**os.environ, "TRYON_JOBS_DIR": str(jobs_dir), "TRYON_WORKERS": "1", "TRYON_JOB_CHUNK_FRAMES": "30", "TRYON_JOB_LEASE_S": "2",
           "TRYON_JOB_POLL_S": "0.1", "TRYON_LOG_LEVEL": "warning"}
    proc = subprocess.Popen([sys.executable, "-m", "service", "--port", str(port), "--log-level", "warning"], cwd=REPO_ROOT, env=env,
                            start_new_session=True)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            pass
        assert proc.poll() is None, "the server exited"
        time.sleep(0.1)
    raise AssertionError("the server did not get ready")


def _kill_group(proc: subprocess.Popen, sig=signal.SIGKILL) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass
    proc.wait(30)


def test_service_killed_during_a_job_finishes_it_after_restart(tmp_path):
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    server = _serve(port, tmp_path)
    try:
        body = {**SLOW, "motion": {"type": "clip", "clip": "dance", "duration_s": 6.0}}
        r = httpx.post(url + "/v1/jobs", json=body, timeout=10)
        assert r.status_code == 202
        job_url = url + r.headers["location"]
        queued = httpx.post(url + "/v1/jobs", json={**body, "format": "glb"}, timeout=10).headers["location"]
        t0 = time.monotonic()
        while httpx.get(job_url, timeout=5).json()["progress"]["frames_done"] == 0:
            assert time.monotonic() - t0 < 60
            time.sleep(0.05)
        _kill_group(server)  # the API, its forkserver and workers: no chance to clean up
        server = _serve(port, tmp_path)
        for job in (job_url, url + queued):
            t0 = time.monotonic()
            while (state := httpx.get(job, timeout=5).json())["state"] not in ("succeeded", "failed", "cancelled"):
                assert time.monotonic() - t0 < 120, state
                time.sleep(0.1)
            assert state["state"] == "succeeded", state
            assert state["progress"]["frames_done"] == 181
            assert httpx.get(job + "/result", timeout=10).status_code == 200
    finally:
        _kill_group(server)


def test_sigterm_drains_an_in_flight_request(tmp_path):
    port = _free_port()
    server = _serve(port, tmp_path)
    result = {}
    try:
        t = threading.Thread(target=lambda: result.update(r=httpx.post(f"http://127.0.0.1:{port}/v1/drape", json=SLOW, timeout=60)))
        t.start()
        time.sleep(0.5)
        server.send_signal(signal.SIGTERM)
        t.join(60)
        assert result["r"].status_code == 200
        assert server.wait(30) in (0, -signal.SIGTERM)  # uvicorn re-raises the signal after its graceful shutdown
    finally:
        _kill_group(server)
