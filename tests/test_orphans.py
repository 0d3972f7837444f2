"""Audit D5: kill -9 of the API leaves no worker behind, even one busy with a long drape (the
pool's workers are children of the forkserver, so they watch the API process itself)."""
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

from tests.conftest import REPO_ROOT

pytestmark = pytest.mark.timeout(180)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _live_members(pgid: int) -> list[str]:
    """Processes of the process group that are not zombies (a zombie has exited)."""
    out = subprocess.run(["ps", "-ww", "-eo", "pid=,pgid=,stat=,args="], capture_output=True, text=True, check=True).stdout
    rows = [line.split(None, 3) for line in out.splitlines()]
    return [" ".join(r) for r in rows if len(r) >= 3 and r[1] == str(pgid) and not r[2].startswith("Z")]


def test_killing_the_api_stops_its_busy_worker_within_seconds(tmp_path):
    port = _free_port()
    env = {**os.environ, "TRYON_WORKERS": "1", "TRYON_JOBS_DIR": str(tmp_path), "TRYON_LOG_LEVEL": "warning"}
    api = subprocess.Popen([sys.executable, "-m", "service", "--port", str(port)], cwd=REPO_ROOT, env=env, start_new_session=True,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while True:
            assert time.monotonic() < deadline and api.poll() is None, "the API did not become ready"
            try:
                if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.3)
        long = {"motion": {"type": "clip", "clip": "dance", "duration_s": 8}, "garments": [{"id": "tshirt"}], "format": "npz"}
        threading.Thread(target=lambda: _ignore(lambda: httpx.post(f"http://127.0.0.1:{port}/v1/drape", json=long, timeout=120)), daemon=True).start()
        time.sleep(2.0)  # the worker is busy with the drape (~10 s of work)
        workers = [m for m in _live_members(api.pid) if "forkserver" in m]
        assert len(workers) >= 2, _live_members(api.pid)  # the forkserver and its worker
        os.kill(api.pid, signal.SIGKILL)
        api.wait(10)
        t0 = time.monotonic()
        while _live_members(api.pid) and time.monotonic() - t0 < 10:
            time.sleep(0.2)
        assert _live_members(api.pid) == [], "processes outlived the API"
        assert time.monotonic() - t0 < 5
    finally:
        try:
            os.killpg(api.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def _ignore(call):
    try:
        call()
    except httpx.HTTPError:
        pass
