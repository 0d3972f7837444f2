"""The real containers: build the images with podman and run the compose stack (API replicas behind
nginx, Redis, an RQ worker, the job volume) on loopback ports, then use it as a client would.

Steps, each timed (printed, and written to build/containers/timings.json):
  base      debootstrap a Debian bookworm rootfs with python3.11 and import it as the base image
            (no registry is reachable here: nothing is pulled)
  images    a node image (the host's node + npm on that base) for the three.js stage, an infra image
            (Debian's redis-server and nginx), and the project image from docker/Dockerfile with
            BASE/NODE_BASE pointing at them; the image's size is recorded
  up        podman-compose up of docker/compose.loopback.yml; every replica ready; the image's
            HEALTHCHECK passes in a running replica
  drape     the README request through nginx, the glb checked by the Khronos validator
  job       a job that the worker container runs; its result fetched
  kill      16 clients drape through nginx while one API replica is killed: every drape gets its glb
            (busy answers are 503 + Retry-After, which the clients honour); no other error
  restart   a job submitted just before the whole stack goes down is finished and fetchable after
            it comes back up, and so is the result of the job before it (the volume)
  teardown  down -v, and every image the test built removed

Needs root, podman (with runc), debootstrap and the network to Debian's and PyPI's mirrors (what
the image build downloads). `.ci/run` runs it as its own step after the suite; elsewhere it runs
when TRYON_CONTAINER_TEST=1."""
from __future__ import annotations

import collections
import json
import os
import random
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from tests.conftest import REPO_ROOT, validate_glb

pytestmark = [
    pytest.mark.containers,
    pytest.mark.timeout(900),
    pytest.mark.skipif(os.environ.get("TRYON_CONTAINER_TEST") != "1",
                       reason="builds and runs the container images with podman: TRYON_CONTAINER_TEST=1 (.ci/run does, after the suite)"),
]

WORK = REPO_ROOT / "build" / "containers"
COMPOSE_FILE = REPO_ROOT / "docker" / "compose.loopback.yml"
PROJECT = "tryonci"
TAG = "ci-test"
IMAGE, NODE_IMAGE, INFRA_IMAGE, BASE_IMAGE = (f"localhost/{name}:{TAG}" for name in ("tryon", "tryon-node", "tryon-infra", "tryon-base"))
PORTS = {"redis": 16379, "api1": 18001, "api2": 18002, "proxy": 18080}  # compose.loopback.yml, nginx.loopback.conf
PROXY = f"http://127.0.0.1:{PORTS['proxy']}"
README_REQUEST = {"body": {"phenotypes": {"gender": 0.5, "age": 0.8, "weight": 0.5, "height": 0.5}},
                  "motion": {"type": "clip", "clip": "walk", "duration_s": 2.0},
                  "garments": [{"id": "tshirt"}], "format": "glb"}
CONTAINERS_CONF = """[containers]
# the sandbox refuses setrlimit: no default ulimits for the containers
default_ulimits = []
[engine]
runtime = "runc"
"""


class Steps:
    """Wall time of each named step, in seconds."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.facts: dict[str, object] = {}

    def __call__(self, name: str):
        steps = self

        class _Timer:
            def __enter__(self):
                self.t0 = time.monotonic()
                print(f"[containers] {name} ...", flush=True)

            def __exit__(self, *exc):
                steps.seconds[name] = round(time.monotonic() - self.t0, 1)
                print(f"[containers] {name}: {steps.seconds[name]} s", flush=True)

        return _Timer()

    def write(self) -> None:
        WORK.mkdir(parents=True, exist_ok=True)
        report = {"seconds": self.seconds, "total_s": round(sum(self.seconds.values()), 1), **self.facts}
        (WORK / "timings.json").write_text(json.dumps(report, indent=2) + "\n")
        print("[containers] " + json.dumps(report), flush=True)


def _run(cmd: list[str], env: dict, timeout: float = 600, check: bool = True, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout, **kw)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} -> {proc.returncode}\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    return proc


def _podman_env() -> dict:
    env = dict(os.environ)
    if "CONTAINERS_CONF" not in env:
        conf = WORK / "containers.conf"
        conf.parent.mkdir(parents=True, exist_ok=True)
        conf.write_text(CONTAINERS_CONF)
        env["CONTAINERS_CONF"] = str(conf)
    env.update(TRYON_IMAGE=IMAGE, TRYON_INFRA_IMAGE=INFRA_IMAGE)
    return env


def _compose(env: dict, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    exe = shutil.which("podman-compose", path=str(Path(sys.executable).parent)) or shutil.which("podman-compose")
    assert exe, "podman-compose not installed (the test extra has it)"
    return _run([exe, "-p", PROJECT, "-f", str(COMPOSE_FILE), *args], env, timeout=timeout)


def _container(service: str) -> str:
    return f"{PROJECT}_{service}_1"


def _wait_ready(url: str, seconds: float = 180) -> None:
    t0 = time.monotonic()
    while True:
        try:
            if httpx.get(url + "/readyz", timeout=3).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        assert time.monotonic() - t0 < seconds, f"{url} never became ready"
        time.sleep(0.5)


def _wait_job(location: str, seconds: float = 180) -> dict:
    t0 = time.monotonic()
    while True:
        try:
            state = httpx.get(PROXY + location, timeout=5).json()
        except httpx.HTTPError:  # the stack is coming back up
            state = {"state": "unreachable"}
        if state["state"] == "succeeded":
            return state
        assert state["state"] in ("queued", "running", "unreachable") and time.monotonic() - t0 < seconds, state
        time.sleep(0.3)


def _glb(location: str, tmp_path: Path, name: str) -> Path:
    r = httpx.get(PROXY + location + "/result", timeout=30)
    assert r.status_code == 200 and r.content[:4] == b"glTF", (r.status_code, r.content[:200])
    path = tmp_path / name
    path.write_bytes(r.content)
    return path


def _drape_under_kill(victim: str, env: dict, clients: int = 16, before_s: float = 8.0, after_s: float = 14.0,
                      give_up_s: float = 120.0) -> dict:
    """`clients` threads drape through nginx in a loop (short walks, a new body each time so that
    no answer comes from the cache); `victim` is SIGKILLed after `before_s`. Each client behaves
    as the API asks: on a 503 problem+json with Retry-After (a busy survivor, or nginx finding no
    replica that could take it) it waits that long and resends, for up to `give_up_s`; a client
    starts no new drape after the window but finishes the one it has. Any other answer, any
    transport error, a 503 without Retry-After or a drape given up on is a client-visible error."""
    answers: collections.Counter = collections.Counter()
    finals: collections.Counter = collections.Counter()
    finals_after_kill: collections.Counter = collections.Counter()
    killed = threading.Event()
    lock = threading.Lock()
    stop = time.monotonic() + before_s + after_s

    def post(http: httpx.Client, body: dict) -> tuple[object, float | None]:
        """One answer's outcome, and the seconds to wait before resending (None: do not)."""
        try:
            r = http.post(PROXY + "/v1/drape", json=body)
        except httpx.HTTPError as e:
            return type(e).__name__, None
        if r.status_code == 200:
            return (200 if r.content[:4] == b"glTF" else "not glTF"), None
        if r.status_code == 503 and r.headers.get("content-type", "").startswith("application/problem+json"):
            try:
                return 503, min(float(r.headers["retry-after"]), 5.0)
            except (KeyError, ValueError):
                return "503 without Retry-After", None
        return r.status_code, None

    def client(seed: int) -> None:
        rng = random.Random(seed)
        with httpx.Client(timeout=90) as http:
            while time.monotonic() < stop:
                body = {**README_REQUEST, "body": {"phenotypes": {"gender": 0.5, "age": 0.8, "weight": round(rng.uniform(0.2, 0.8), 5), "height": 0.5}},
                        "motion": {"type": "clip", "clip": "walk", "duration_s": 0.25}}
                started_after_kill = killed.is_set()
                deadline = time.monotonic() + give_up_s
                while True:
                    outcome, wait_s = post(http, body)
                    with lock:
                        answers[outcome] += 1
                    if wait_s is None:
                        break
                    if time.monotonic() + wait_s > deadline:
                        outcome = "given up"
                        break
                    time.sleep(wait_s)
                with lock:
                    finals[outcome] += 1
                    if started_after_kill:
                        finals_after_kill[outcome] += 1
                if outcome != 200:
                    time.sleep(0.2)

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    time.sleep(before_s)
    _run(["podman", "kill", victim], env)
    killed.set()
    for t in threads:
        t.join()
    log = _run(["podman", "logs", _container("proxy")], env)
    retried = sum(1 for line in log.stdout.splitlines() if '"uri":"/v1/drape"' in line and '"upstream":"' in line and ", " in line.split('"upstream":"', 1)[1].split('"', 1)[0])
    nginx_errors = {what: log.stderr.count(what) for what in ("Connection refused", "prematurely closed", "Connection reset", "no live upstreams")}
    survivor = _run(["podman", "logs", _container("api2")], env)
    busy = (survivor.stdout + survivor.stderr).count("POST /v1/drape 503")
    return {"clients": clients, "answers": {str(k): v for k, v in answers.items()},
            "drapes": {str(k): v for k, v in finals.items()},
            "drapes_started_after_kill": {str(k): v for k, v in finals_after_kill.items()}, "retried_by_nginx": retried,
            "nginx_errors": nginx_errors, "survivor_503": busy}


def _free(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


def _debootstrap(rootfs: Path, env: dict) -> None:
    """A minimal Debian bookworm with Python 3.11 (+ venv), less apt's caches, docs and locales."""
    if not (rootfs / "usr" / "bin" / "python3.11").exists():
        shutil.rmtree(rootfs, ignore_errors=True)
        _run(["debootstrap", "--variant=minbase", "--include=python3.11,python3.11-venv,python3-distutils,ca-certificates",
              "bookworm", str(rootfs), "http://deb.debian.org/debian"], env, timeout=600)
    for pattern in ("var/cache/apt/archives/*.deb", "var/lib/apt/lists/*", "usr/share/doc/*", "usr/share/man/*", "usr/share/locale/*"):
        for p in rootfs.glob(pattern):
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()


def _build_base(env: dict) -> None:
    rootfs = WORK / "rootfs"
    _debootstrap(rootfs, env)
    tar = subprocess.Popen(["tar", "-C", str(rootfs), "-c", "."], stdout=subprocess.PIPE)
    _run(["podman", "import", "-", BASE_IMAGE], env, stdin=tar.stdout)
    assert tar.wait() == 0


def _build_images(env: dict, steps: Steps) -> None:
    node_ctx = WORK / "node"
    shutil.rmtree(node_ctx, ignore_errors=True)
    node_ctx.mkdir(parents=True)
    shutil.copy2(shutil.which("node"), node_ctx / "node")
    shutil.copytree(Path(shutil.which("npm")).resolve().parents[1], node_ctx / "npm", symlinks=True)
    (node_ctx / "Containerfile").write_text(
        f"FROM {BASE_IMAGE}\nCOPY node /usr/bin/node\nCOPY npm /usr/lib/node_modules/npm\n"
        "RUN ln -s /usr/lib/node_modules/npm/bin/npm-cli.js /usr/bin/npm && node --version && npm --version\n")
    _run(["podman", "build", "-q", "--network", "host", "-t", NODE_IMAGE, str(node_ctx)], env)

    infra_ctx = WORK / "infra"
    infra_ctx.mkdir(parents=True, exist_ok=True)
    (infra_ctx / "Containerfile").write_text(
        f"FROM {BASE_IMAGE}\nRUN apt-get update && apt-get install -y --no-install-recommends redis-server nginx "
        "&& rm -rf /var/lib/apt/lists/*\n")
    _run(["podman", "build", "-q", "--network", "host", "-t", INFRA_IMAGE, str(infra_ctx)], env)

    # this host's CA bundle (it may sit behind a TLS-intercepting proxy) for pip and npm, build only
    ca = "/etc/ssl/certs/ca-certificates.crt"
    ca_args = ["-v", f"{ca}:/etc/ssl/host-ca.crt:ro", "--build-arg", "PIP_CERT=/etc/ssl/host-ca.crt",
               "--build-arg", "NODE_EXTRA_CA_CERTS=/etc/ssl/host-ca.crt"] if Path(ca).is_file() else []
    # --format docker: OCI images have no HEALTHCHECK
    _run(["podman", "build", "--format", "docker", "--network", "host", *ca_args,
          "--build-arg", f"BASE={BASE_IMAGE}", "--build-arg", f"NODE_BASE={NODE_IMAGE}",
          "--build-arg", "BUILD_PACKAGES=g++ python3.11-dev",  # the Debian base has no Python headers
          "-f", str(REPO_ROOT / "docker" / "Dockerfile"), "-t", IMAGE, str(REPO_ROOT)], env, timeout=900)
    size = int(_run(["podman", "image", "inspect", "--format", "{{.Size}}", IMAGE], env).stdout.strip())
    base = int(_run(["podman", "image", "inspect", "--format", "{{.Size}}", BASE_IMAGE], env).stdout.strip())
    du = _run(["podman", "run", "--rm", "--network", "none", "--entrypoint", "du", IMAGE, "-sk", "/opt/venv", "/app/assets",
               "/app/node_modules/three", "/app/inference", "/app/service"], env).stdout
    packages = _run(["podman", "run", "--rm", "--network", "none", "--entrypoint", "sh", IMAGE, "-c",
                     "cd /opt/venv/lib/python3.11/site-packages && du -sk * | sort -rn | head -8"
                     " && find . -name '*.pyc' -printf '%s\\n' | awk '{s += $1} END {print int(s / 1024), \"total\"}'"], env).stdout
    steps.facts["python_packages_mb"] = {(line.split()[1] if line.split()[1] != "total" else "all .pyc"): round(int(line.split()[0]) * 1024 / 1e6, 1)
                                         for line in packages.splitlines()}
    steps.facts["image_mb"] = round(size / 1e6, 1)
    steps.facts["image_parts_mb"] = {"base": round(base / 1e6, 1),
                                     **{line.split()[1]: round(int(line.split()[0]) * 1024 / 1e6, 1) for line in du.splitlines()}}


def _images(env: dict) -> set[str]:
    return set(_run(["podman", "images", "-a", "-q", "--no-trunc"], env).stdout.split())


def test_the_compose_stack_runs_in_podman(tmp_path):
    for tool in ("podman", "debootstrap", "node", "npm", "tar"):
        assert shutil.which(tool), f"{tool} not installed (.ci/run installs podman, runc and debootstrap)"
    busy = [f"{name}:{port}" for name, port in PORTS.items() if not _free(port)]
    assert not busy, f"ports in use: {busy}"
    env = _podman_env()
    steps = Steps()
    images_before = _images(env)
    try:
        with steps("base"):
            _build_base(env)
        with steps("images"):
            _build_images(env, steps)

        with steps("up"):
            _compose(env, "up", "-d")
            for name in ("api1", "api2", "proxy"):
                _wait_ready(f"http://127.0.0.1:{PORTS[name]}")
            # the image's HEALTHCHECK, run by hand (podman schedules it through systemd, absent here)
            _run(["podman", "healthcheck", "run", _container("api1")], env)

        with steps("drape"):
            r = httpx.post(PROXY + "/v1/drape", json=README_REQUEST, timeout=120)
            assert r.status_code == 200 and r.headers["content-type"].startswith("model/gltf-binary"), r.text[:500]
            (tmp_path / "readme.glb").write_bytes(r.content)
            assert validate_glb(tmp_path / "readme.glb")["issues"]["numErrors"] == 0
            # what the image trims must not be what a page loads: the viewer's three.js, the API docs' Swagger UI
            for path in ("/viewer/", "/viewer/vendor/three/build/three.module.js", "/viewer/vendor/three/examples/jsm/loaders/GLTFLoader.js", "/docs"):
                assert httpx.get(PROXY + path, timeout=10).status_code == 200, path
            docs = httpx.get(PROXY + "/docs", timeout=10).text
            assets = re.findall(r'(?:src|href)="(/[^"]+\.(?:js|css))"', docs)
            assert len(assets) >= 2, docs[:1000]
            for asset in assets:
                assert httpx.get(PROXY + asset, timeout=10).status_code == 200, asset

        with steps("job"):
            r = httpx.post(PROXY + "/v1/jobs", json=README_REQUEST, timeout=30)
            assert r.status_code == 202, r.text
            first_job = r.headers["location"]
            _wait_job(first_job)
            assert validate_glb(_glb(first_job, tmp_path, "job.glb"))["issues"]["numErrors"] == 0
            job_id = first_job.rstrip("/").rsplit("/", 1)[-1]
            worker_log = _run(["podman", "logs", _container("worker")], env)
            assert job_id in worker_log.stdout + worker_log.stderr  # run by the worker container

        with steps("kill"):
            load = _drape_under_kill(_container("api1"), env)
            steps.facts["kill_one_replica"] = load
            assert set(load["answers"]) <= {"200", "503"}, load  # 503s are problem+json with Retry-After (post())
            assert set(load["drapes"]) == {"200"}, load  # every drape, resent as the 503s asked, got its glb
            assert load["drapes_started_after_kill"].get("200", 0) >= 1, load  # the survivor served them

        with steps("restart"):
            body = {**README_REQUEST, "body": {"phenotypes": {"gender": 0.3, "age": 0.9, "weight": 0.7, "height": 0.4}}}
            r = httpx.post(PROXY + "/v1/jobs", json=body, timeout=30)
            assert r.status_code == 202, r.text
            second_job = r.headers["location"]
            before = httpx.get(PROXY + second_job, timeout=5).json()["state"]
            _compose(env, "down", timeout=300)  # keeps the volumes
            _compose(env, "up", "-d")
            for name in ("api1", "api2", "proxy"):
                _wait_ready(f"http://127.0.0.1:{PORTS[name]}")
            after = httpx.get(PROXY + second_job, timeout=5).json()["state"]
            _wait_job(second_job)
            steps.facts["job_across_restart"] = {"state_at_down": before, "state_after_up": after}
            assert validate_glb(_glb(second_job, tmp_path, "after_restart.glb"))["issues"]["numErrors"] == 0
            _glb(first_job, tmp_path, "first_after_restart.glb")
    finally:
        with steps("teardown"):
            _compose(env, "down", "-v", timeout=300)
            new = _images(env) - images_before
            if new:
                _run(["podman", "rmi", "-f", *sorted(new)], env, check=False)
            if os.environ.get("TRYON_CONTAINER_TEST_KEEP_ROOTFS") != "1":
                shutil.rmtree(WORK / "rootfs", ignore_errors=True)
        steps.write()
    assert not (_images(env) - images_before), "the test left images behind"
