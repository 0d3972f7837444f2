"""Audit D2: a full disk under the job store. On a small tmpfs (a real ENOSPC), a running job
whose result no longer fits fails with a 507 problem and leaves no temporary file, DELETE still
works, new jobs get 507 and /readyz reports the store, until the disk has room again; then jobs
run as before."""
from __future__ import annotations

import errno
import os
import subprocess
import time

import pytest

BODY = {"motion": {"type": "clip", "clip": "dance", "duration_s": 2.0}, "garments": [{"id": "tshirt"}], "format": "npz",
        "options": {"include_body": False, "guard": False}}
# 241 frames, ~13 MB of npz, in chunks of 60; with the collision stages (~15 ms per frame) it runs
# for seconds, so the disk fills while it runs
LONG = {**BODY, "motion": {"type": "clip", "clip": "dance", "duration_s": 8.0}, "options": {"include_body": False}}


@pytest.fixture
def small_disk(tmp_path):
    """A 32 MiB tmpfs (needs mount rights: root with CAP_SYS_ADMIN, as in CI's container)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=32m", "tmpfs", str(disk)], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({proc.stderr.strip()[:80]})")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def _fill(path) -> None:
    """Write until the filesystem is full."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT)
    try:
        while True:
            os.write(fd, b"\0" * 4096)
    except OSError as exc:
        assert exc.errno == errno.ENOSPC
    finally:
        os.close(fd)


def _wait(client, job_id: str, timeout_s: float = 60.0) -> dict:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} still {job['state']}")


def test_a_full_disk_fails_the_job_cleanly_and_recovers(small_disk, settings, runtime):
    from fastapi.testclient import TestClient

    from service.app import create_app

    s = settings.model_copy(update={"jobs_dir": small_disk, "worker_mode": "thread", "workers": 1, "job_poll_s": 0.05, "job_chunk_frames": 60})
    with TestClient(create_app(s, runtime), raise_server_exceptions=False) as client:
        assert client.get("/readyz").status_code == 200
        r = client.post("/v1/jobs", json=LONG)
        assert r.status_code == 202, r.text
        t0 = time.monotonic()
        while client.get(f"/v1/jobs/{r.json()['id']}").json()["progress"]["frames_done"] == 0:
            assert time.monotonic() - t0 < 60
            time.sleep(0.05)
        _fill(small_disk / "filler")  # while the job runs: its result no longer fits
        job = _wait(client, r.json()["id"])
        assert job["state"] == "failed" and job["error"]["status"] == 507, job
        assert not list((small_disk / "results").glob("*.tmp")), "a partial result file was left"
        refused = client.post("/v1/jobs", json=BODY)
        assert refused.status_code == 507 and refused.headers["retry-after"], refused.text
        ready = client.get("/readyz")
        assert ready.status_code == 503 and "disk is full" in ready.json()["detail"]
        assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert client.get(f"/v1/jobs/{job['id']}").status_code == 404

        (small_disk / "filler").unlink()
        t0 = time.monotonic()
        while client.get("/readyz").status_code != 200:
            assert time.monotonic() - t0 < 30, "the store did not recover"
            time.sleep(0.1)
        again = client.post("/v1/jobs", json=BODY)
        assert again.status_code == 202
        assert _wait(client, again.json()["id"])["state"] == "succeeded"


class _FullOnce:
    """A connection whose next write fails as SQLite does on a full disk, until the store frees
    its reserve (wherever a tmpfs cannot be mounted, this is the store's half of the test above)."""

    def __init__(self, db, reserve):
        self.db, self.reserve = db, reserve

    def execute(self, sql, args=()):
        import sqlite3

        if not sql.lstrip().upper().startswith("SELECT") and self.reserve.exists():
            raise sqlite3.OperationalError("database or disk is full")
        return self.db.execute(sql, args)

    def close(self):
        self.db.close()


def test_the_store_frees_its_reserve_to_finish_writes_then_refuses_new_jobs(tmp_path, settings):
    from service.errors import ProblemException
    from service.jobs import RESERVE_BYTES, SqliteJobStore
    from service.schemas import DrapeRequest

    store = SqliteJobStore(settings.model_copy(update={"jobs_dir": tmp_path}))
    assert store.reserve.stat().st_size == RESERVE_BYTES and store.ping()
    store.db = _FullOnce(store.db, store.reserve)
    record = store.create(DrapeRequest.model_validate(BODY))  # the write fails, the reserve goes, the retry lands
    assert store.get(record.id).state == "queued" and not store.reserve.exists()
    assert store.degraded and not store.ping()
    with pytest.raises(ProblemException) as refused:
        store.create(DrapeRequest.model_validate(BODY))
    assert refused.value.status == 507
    assert store.cancel(record.id) is not None and store.get(record.id).state == "cancelled"
    assert store.restore_reserve() and not store.degraded and store.reserve.exists()
    store.close()
