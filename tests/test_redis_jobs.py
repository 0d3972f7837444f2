"""Jobs on the Redis backend (RQ), against a real redis-server started here (Debian package
redis-server; .ci/run installs it) and a real worker process (``python -m service.worker``)."""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.config import Settings
from tests.conftest import REPO_ROOT

pytestmark = [pytest.mark.timeout(240), pytest.mark.skipif(shutil.which("redis-server") is None, reason="redis-server not installed (apt-get install redis-server)")]

BODY = {"motion": {"type": "clip", "clip": "dance", "duration_s": 2.0}, "garments": [{"id": "tshirt"}], "format": "npz",
        "options": {"include_body": False}}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory):
    """A real redis-server on a free port (skips where none is installed: `.ci/run` installs it)."""
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server not installed (apt-get install redis-server)")
    port = _free_port()
    proc = subprocess.Popen(["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                             "--dir", str(tmp_path_factory.mktemp("redis"))], stdout=subprocess.DEVNULL)
    from redis import Redis

    url = f"redis://127.0.0.1:{port}/0"
    t0 = time.monotonic()
    while True:
        try:
            if Redis.from_url(url).ping():
                break
        except Exception:  # noqa: BLE001
            assert time.monotonic() - t0 < 20, "redis-server did not start"
            time.sleep(0.05)
    yield url
    proc.terminate()
    proc.wait(10)


@pytest.fixture
def redis_settings(redis_url, tmp_path):
    return Settings().model_copy(update={"jobs_backend": "redis", "redis_url": redis_url, "redis_queue": f"q{tmp_path.name}",
                                         "jobs_dir": tmp_path / "jobs", "worker_mode": "thread", "workers": 1, "job_chunk_frames": 20})


def _worker(settings, burst=False) -> subprocess.Popen:
    env = {**os.environ, "TRYON_JOBS_DIR": str(settings.jobs_dir), "TRYON_JOB_CHUNK_FRAMES": "20", "TRYON_LOG_LEVEL": "warning"}
    args = [sys.executable, "-m", "service.worker", "--redis-url", settings.redis_url, "--queue", settings.redis_queue] + (["--burst"] if burst else [])
    return subprocess.Popen(args, cwd=REPO_ROOT, env=env, start_new_session=True)


def _wait(client, url, states=("succeeded", "failed", "cancelled"), timeout_s=120):
    t0 = time.monotonic()
    while (job := client.get(url).json())["state"] not in states:
        assert time.monotonic() - t0 < timeout_s, job
        time.sleep(0.05)
    return job


def _wait_for_progress(client, url, timeout_s=60):
    """Until the job has reported its first chunk (it is mid-way)."""
    t0 = time.monotonic()
    while client.get(url).json()["progress"]["frames_done"] == 0:
        assert time.monotonic() - t0 < timeout_s
        time.sleep(0.02)


def _horses(worker: subprocess.Popen) -> list[str]:
    """The RQ worker's work-horse pids (its children)."""
    return subprocess.run(["pgrep", "-P", str(worker.pid)], capture_output=True, text=True).stdout.split()


def test_jobs_run_on_a_separate_rq_worker(redis_settings, runtime):
    with TestClient(create_app(redis_settings, runtime), raise_server_exceptions=False) as c:
        assert c.get("/readyz").json()["jobs_backend"] == "redis"
        good = c.post("/v1/jobs", json=BODY)
        assert good.status_code == 202, good.text
        bad = c.post("/v1/jobs", json={**BODY, "motion": {"type": "bvh", "bvh": "HIERARCHY\nROOT Hips\n{"}})
        cancelled = c.post("/v1/jobs", json=BODY).headers["location"]
        assert c.get(good.headers["location"]).json()["state"] == "queued"  # no worker yet
        assert c.delete(cancelled).status_code == 204
        worker = _worker(redis_settings, burst=True)  # another process (another machine in docker-compose)
        try:
            job = _wait(c, good.headers["location"])
            assert job["state"] == "succeeded", job
            assert job["progress"]["frames_done"] == job["progress"]["frames_total"] == 61
            r = c.get(job["result_url"])
            assert r.status_code == 200 and r.headers["content-type"] == "application/x-npz" and len(r.content) == job["result_bytes"]
            failed = _wait(c, bad.headers["location"])
            assert failed["state"] == "failed" and failed["error"]["status"] == 422
            assert c.get(cancelled).json()["state"] == "cancelled"
            assert worker.wait(120) == 0  # burst: exits when the queue is empty
        finally:
            if worker.poll() is None:
                os.killpg(worker.pid, signal.SIGKILL)
        assert "tryon_jobs{state=\"succeeded\"} 1.0" in c.get("/metrics").text
        assert c.delete(good.headers["location"]).status_code == 204
        assert c.get(good.headers["location"]).status_code == 404


def test_a_killed_work_horse_is_retried(redis_settings, runtime):
    """SIGKILL of the process running the job: RQ records the failure and re-runs it (Retry)."""
    with TestClient(create_app(redis_settings, runtime), raise_server_exceptions=False) as c:
        # a job runs in chunks, so it is caught mid-way
        options = {"include_body": False, "guard": True, "fit": "retarget", "dynamics": "none"}
        url = c.post("/v1/jobs", json={**BODY, "options": options}).headers["location"]
        worker = _worker(redis_settings)
        try:
            _wait_for_progress(c, url)
            horses = _horses(worker)
            assert horses, "no work-horse"
            os.kill(int(horses[0]), signal.SIGKILL)
            job = _wait(c, url)
            assert job["state"] == "succeeded", job
        finally:
            os.killpg(worker.pid, signal.SIGKILL)
            worker.wait(10)


def test_readyz_fails_when_redis_is_unreachable(runtime, tmp_path):
    s = Settings().model_copy(update={"jobs_backend": "redis", "redis_url": f"redis://127.0.0.1:{_free_port()}/0", "jobs_dir": tmp_path,
                                      "worker_mode": "thread", "workers": 1})
    with TestClient(create_app(s, runtime), raise_server_exceptions=False) as c:
        assert c.get("/readyz").status_code == 503
        r = c.post("/v1/jobs", json=BODY)
        assert r.status_code == 503 and r.headers["retry-after"] == "5"


def test_redis_job_quotas_answer_429(redis_settings, runtime, tmp_path):
    """No worker runs: every job stays queued, so the per-key and total bounds are reached."""
    keys = tmp_path / "keys"
    keys.write_text("key-a\nkey-b\n")
    s = redis_settings.model_copy(update={"api_keys_file": keys, "job_max_pending_per_key": 2, "job_max_pending": 3,
                                          "redis_queue": redis_settings.redis_queue + "-quota"})
    with TestClient(create_app(s, runtime), raise_server_exceptions=False) as c:
        a = [c.post("/v1/jobs", json=BODY, headers={"X-API-Key": "key-a"}) for _ in range(3)]
        assert [r.status_code for r in a] == [202, 202, 429], a[-1].text
        assert "your jobs" in a[-1].json()["detail"] and a[-1].headers["retry-after"]
        b = [c.post("/v1/jobs", json=BODY, headers={"X-API-Key": "key-b"}) for _ in range(2)]
        assert [r.status_code for r in b] == [202, 429] and "queue is full" in b[-1].json()["detail"]
        assert c.delete(a[0].headers["location"], headers={"X-API-Key": "key-a"}).status_code == 204
        assert c.post("/v1/jobs", json=BODY, headers={"X-API-Key": "key-a"}).status_code == 202  # the cancelled job's slot


def test_a_job_whose_worker_died_is_requeued_within_a_minute(redis_settings, runtime):
    """Audit D3: kill -9 of the worker and its work-horse mid-job, and a new worker at once: the
    job leaves 'running' once ``job_abandoned_s`` pass without a heartbeat (not after RQ's 10 min
    maintenance), and the new worker finishes it."""
    s = redis_settings.model_copy(update={"job_abandoned_s": 10.0})
    options = {"include_body": False, "guard": True, "fit": "retarget", "dynamics": "none"}
    long = {**BODY, "motion": {"type": "clip", "clip": "dance", "duration_s": 8.0}, "options": options}  # 241 frames in chunks of 20
    with TestClient(create_app(s, runtime), raise_server_exceptions=False) as c:
        url = c.post("/v1/jobs", json=long).headers["location"]
        first = _worker(s)
        try:
            _wait_for_progress(c, url)
        finally:
            horses = _horses(first)
            for pid in [first.pid, *map(int, horses)]:  # the worker and its work-horse (which has a session of its own)
                os.kill(pid, signal.SIGKILL)
            first.wait(10)
        assert horses, "no work-horse"
        killed = time.monotonic()
        assert c.get(url).json()["state"] == "running"
        second = _worker(s)
        try:
            while c.get(url).json()["state"] == "running" and c.get(url).json()["progress"]["frames_done"] > 0:
                assert time.monotonic() - killed < 60, "the abandoned job still shows running"
                time.sleep(0.2)
            requeued = time.monotonic() - killed
            assert requeued < s.job_abandoned_s + s.job_abandoned_s / 4 + 10
            job = _wait(c, url)
            assert job["state"] == "succeeded", job
        finally:
            os.killpg(second.pid, signal.SIGKILL)
            second.wait(10)
