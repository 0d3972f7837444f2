"""Asynchronous jobs, embedded backend: a SQLite table plus result files on disk, run by this
process's worker pool. An accepted job (its row committed, fsynced, before the 202) is never
lost: a job whose owner dies is re-queued (at start-up for this host's own dead processes, after
``job_lease_s`` without a lease renewal for any other), up to ``job_max_attempts`` runs.

A full disk does not wedge the store: ``RESERVE_BYTES`` of ballast (``jobs_dir/reserve``) are
set aside at start-up; when a write fails for lack of space the ballast is deleted and the write
retried, so that running jobs can still be finished (failed with a 507 problem), cancelled and
deleted. The store is then ``degraded``: new jobs get 507, queued jobs wait (they are not lost),
``/readyz`` says so, until the disk has room for the ballast again.

Schema (one table; the request is stored as validated JSON, results live in ``results/<id>.<fmt>``):

    jobs(id TEXT PRIMARY KEY,              -- uuid4 hex
         state TEXT,                       -- queued | running | succeeded | failed | cancelled
         request TEXT, format TEXT,
         frames_done INTEGER, frames_total INTEGER,   -- progress (total known once the motion is imported)
         attempts INTEGER,                 -- runs started (claims)
         owner TEXT, lease_until REAL,     -- running: "host:pid" of the runner and its lease (unix s)
         error TEXT,                       -- failed: the problem document (JSON)
         result_bytes INTEGER, headers TEXT,
         created_at REAL, updated_at REAL, started_at REAL, finished_at REAL,
         expires_at REAL,                  -- finished: row and result deleted after this
         client TEXT)                      -- who asked (service.auth.client_id), for the per-key quota
    INDEX jobs_queue ON jobs(state, created_at);  INDEX jobs_expiry ON jobs(expires_at)
"""
from __future__ import annotations

import asyncio
import errno
import json
import logging
import os
import shutil
import socket
import sqlite3
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from service.config import Settings
from service.errors import ProblemDetail, ProblemException
from service.metrics import Metrics
from service.schemas import DrapeRequest

log = logging.getLogger(__name__)

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINISHED = ("succeeded", "failed", "cancelled")
MEDIA_TYPES = {"glb": "model/gltf-binary", "npz": "application/x-npz"}

SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    state TEXT NOT NULL CHECK (state IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    request TEXT NOT NULL,
    format TEXT NOT NULL,
    frames_done INTEGER NOT NULL DEFAULT 0,
    frames_total INTEGER,
    attempts INTEGER NOT NULL DEFAULT 0,
    owner TEXT,
    lease_until REAL,
    error TEXT,
    result_bytes INTEGER,
    headers TEXT,
    created_at REAL NOT NULL,
    updated_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    expires_at REAL,
    client TEXT
);
CREATE INDEX IF NOT EXISTS jobs_queue ON jobs(state, created_at);
CREATE INDEX IF NOT EXISTS jobs_expiry ON jobs(expires_at);
"""


@dataclass
class JobRecord:
    id: str
    state: str
    format: str
    frames_done: int = 0
    frames_total: int | None = None
    attempts: int = 0
    created_at: float = 0.0
    updated_at: float = 0.0
    finished_at: float | None = None
    expires_at: float | None = None
    error: dict | None = None
    result_bytes: int | None = None
    headers: dict = field(default_factory=dict)


def new_job_id() -> str:
    return uuid.uuid4().hex


RESERVE_BYTES = 8 * 1024 * 1024  # ballast: room for the writes that finish, fail and delete jobs once the disk is full
NO_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def out_of_space(exc: BaseException) -> bool:
    """A write failed for lack of space: ENOSPC / EDQUOT / EFBIG, or SQLite's SQLITE_FULL."""
    if isinstance(exc, OSError) and exc.errno in NO_SPACE:
        return True
    return isinstance(exc, sqlite3.OperationalError) and ("full" in str(exc) or "disk I/O" in str(exc))


def quota_problem(mine: int, everyone: int, s: Settings) -> ProblemDetail:
    """429: this client's unfinished jobs, or the store's, are at their bound."""
    if mine >= s.job_max_pending_per_key:
        detail = f"{mine} of your jobs are queued or running (at most {s.job_max_pending_per_key}); wait for one to finish"
    else:
        detail = f"the job queue is full ({everyone} queued or running, at most {s.job_max_pending}); retry later"
    return ProblemDetail(429, "Too many jobs", detail, headers={"Retry-After": str(max(5, int(s.job_poll_s * 20)))})


def storage_problem() -> ProblemDetail:
    return ProblemDetail(507, "Insufficient storage", "the job store's disk is full; retry later", headers={"Retry-After": "60"})


# Attempts at the store's set-up while another process creates it (``SqliteJobStore``).
SETUP_ATTEMPTS = 20


class SqliteJobStore:
    """The jobs table (thread-safe: one connection behind a lock, autocommit, WAL, fsync on commit)."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.dir = Path(settings.jobs_dir)
        self.results_dir = self.dir / "results"
        self.results_dir.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self.db = sqlite3.connect(self.dir / "jobs.sqlite3", check_same_thread=False, isolation_level=None, timeout=30)
        self.db.row_factory = sqlite3.Row
        for attempt in range(SETUP_ATTEMPTS):
            try:
                self._set_up()
                break
            except sqlite3.OperationalError as exc:
                # two processes creating one new store at once: switching it to WAL does not wait
                # on SQLite's busy timeout, so the second sees "locked"; it tries again shortly
                if "locked" not in str(exc) or attempt == SETUP_ATTEMPTS - 1:
                    raise
                time.sleep(0.05 * (attempt + 1))
        self.host = socket.gethostname()
        self.owner = f"{self.host}:{os.getpid()}"
        self.reserve = self.dir / "reserve"
        self.degraded = False
        self.restore_reserve()

    def _set_up(self) -> None:
        """WAL, fsync on commit, the schema (idempotent)."""
        with self._lock:
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.executescript(SCHEMA)
            if "client" not in {r["name"] for r in self.db.execute("PRAGMA table_info(jobs)")}:  # a store from before the quota
                self.db.execute("ALTER TABLE jobs ADD COLUMN client TEXT")

    def close(self) -> None:
        with self._lock:
            self.db.close()

    def _exec(self, sql: str, args: tuple = ()) -> list[sqlite3.Row]:
        """One statement; a write that fails for lack of space frees the ballast and is retried
        once (the store becomes ``degraded``)."""
        with self._lock:
            try:
                return self.db.execute(sql, args).fetchall()
            except (sqlite3.OperationalError, OSError) as exc:
                if not out_of_space(exc) or not self._release_reserve():
                    raise
                return self.db.execute(sql, args).fetchall()

    def _release_reserve(self) -> bool:
        """Delete the ballast (False when there was none left to free)."""
        if not self.reserve.exists():
            self.degraded = True
            return False
        self.reserve.unlink()
        if not self.degraded:
            log.error("jobs: the disk under %s is full; freed the %d MiB reserve, new jobs are refused (507) until there is room",
                      self.dir, RESERVE_BYTES >> 20)
        self.degraded = True
        return True

    def mark_full(self) -> None:
        """Another writer (a worker's result file) ran out of space: free the ballast, degrade."""
        with self._lock:
            self._release_reserve()

    def restore_reserve(self) -> bool:
        """Write the ballast back when the disk has room for it twice over; clears ``degraded``."""
        if self.reserve.exists() and self.reserve.stat().st_size == RESERVE_BYTES:
            return True
        try:
            if shutil.disk_usage(self.dir).free < 2 * RESERVE_BYTES:
                raise OSError(errno.ENOSPC, "no room for the reserve")
            with open(self.reserve, "wb") as f:
                f.write(b"\0" * RESERVE_BYTES)
                f.flush()
                os.fsync(f.fileno())
        except OSError:
            self.reserve.unlink(missing_ok=True)
            self.degraded = True
            return False
        if self.degraded:
            log.info("jobs: the disk under %s has room again; taking new jobs", self.dir)
        self.degraded = False
        return True

    def ping(self) -> bool:
        """Ready: not degraded by a full disk."""
        return not self.degraded

    # ------------------------------------------------------------------ API side
    def create(self, request: DrapeRequest, client: str = "anonymous", request_json: str | None = None) -> JobRecord:
        """Queue a job, within the quotas (``job_max_pending`` in all, ``job_max_pending_per_key``
        for ``client``), checked and inserted in one statement; 429 past either, 507 while the
        disk is full."""
        if self.degraded:
            raise storage_problem().exception()
        now = time.time()
        job_id = new_job_id()
        s = self.settings
        rows = self._exec(
            "INSERT INTO jobs (id, state, request, format, created_at, updated_at, client) SELECT ?, 'queued', ?, ?, ?, ?, ? "
            "WHERE (SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')) < ? "
            "AND (SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running') AND client = ?) < ? RETURNING id",
            (job_id, request_json or request.model_dump_json(), request.format, now, now, client, s.job_max_pending, client, s.job_max_pending_per_key))
        if not rows:
            raise quota_problem(self.pending(client), self.pending(), s).exception()
        return self.get(job_id)

    def pending(self, client: str | None = None) -> int:
        """Queued + running jobs (of ``client``, or all)."""
        where, args = ("AND client = ?", (client,)) if client is not None else ("", ())
        return int(self._exec(f"SELECT COUNT(*) AS n FROM jobs WHERE state IN ('queued', 'running') {where}", args)[0]["n"])

    def get(self, job_id: str) -> JobRecord | None:
        rows = self._exec("SELECT * FROM jobs WHERE id = ?", (job_id,))
        return _record(rows[0]) if rows else None

    def result_path(self, job_id: str, fmt: str) -> Path:
        return self.results_dir / f"{job_id}.{fmt}"

    def cancel(self, job_id: str) -> JobRecord | None:
        """Cancel a queued or running job (a running one stops at its next chunk); delete a
        finished one and its result. None: no such job."""
        record = self.get(job_id)
        if record is None:
            return None
        now = time.time()
        if record.state in FINISHED:
            self._exec("DELETE FROM jobs WHERE id = ?", (job_id,))
            self.result_path(job_id, record.format).unlink(missing_ok=True)
        else:
            self._exec("UPDATE jobs SET state = 'cancelled', finished_at = ?, updated_at = ?, expires_at = ? WHERE id = ? AND state IN ('queued', 'running')",
                       (now, now, now + self.settings.job_result_ttl_s, job_id))
        return record

    def counts(self) -> dict[str, int]:
        got = {r["state"]: r["n"] for r in self._exec("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state")}
        return {s: int(got.get(s, 0)) for s in STATES}

    # ------------------------------------------------------------------ runner side
    def claim(self) -> tuple[str, str, int] | None:
        """Atomically take the oldest queued job: (id, request JSON, attempts)."""
        now = time.time()
        rows = self._exec(
            "UPDATE jobs SET state = 'running', owner = ?, lease_until = ?, attempts = attempts + 1, started_at = ?, updated_at = ? "
            "WHERE id = (SELECT id FROM jobs WHERE state = 'queued' ORDER BY created_at LIMIT 1) AND state = 'queued' "
            "RETURNING id, request, attempts",
            (self.owner, now + self.settings.job_lease_s, now, now),
        )
        return (rows[0]["id"], rows[0]["request"], rows[0]["attempts"]) if rows else None

    def renew(self, job_id: str, done: int | None = None, total: int | None = None) -> bool:
        """Extend the lease (and record progress); False when the job was cancelled (or taken away)."""
        now = time.time()
        if done is None:
            rows = self._exec("UPDATE jobs SET lease_until = ? WHERE id = ? AND state = 'running' AND owner = ? RETURNING id",
                              (now + self.settings.job_lease_s, job_id, self.owner))
        else:
            rows = self._exec(
                "UPDATE jobs SET lease_until = ?, frames_done = ?, frames_total = ?, updated_at = ? WHERE id = ? AND state = 'running' AND owner = ? RETURNING id",
                (now + self.settings.job_lease_s, done, total, now, job_id, self.owner))
        return bool(rows)

    def finish(self, job_id: str, state: str, *, error: ProblemDetail | None = None, result_bytes: int | None = None,
               headers: dict | None = None, frames: int | None = None) -> bool:
        now = time.time()
        rows = self._exec(
            "UPDATE jobs SET state = ?, error = ?, result_bytes = ?, headers = ?, finished_at = ?, updated_at = ?, expires_at = ?, "
            "owner = NULL, lease_until = NULL, frames_done = COALESCE(?, frames_done), frames_total = COALESCE(?, frames_total) "
            "WHERE id = ? AND state = 'running' AND owner = ? RETURNING id",
            (state, None if error is None else json.dumps(_problem_json(error)), result_bytes, json.dumps(headers or {}), now, now,
             now + self.settings.job_result_ttl_s, frames, frames, job_id, self.owner))
        return bool(rows)

    def release(self, job_id: str) -> None:
        """Give a running job back to the queue (shutdown, worker crash)."""
        self._exec("UPDATE jobs SET state = 'queued', owner = NULL, lease_until = NULL, updated_at = ? WHERE id = ? AND state = 'running' AND owner = ?",
                   (time.time(), job_id, self.owner))

    def recover(self, startup: bool = False) -> int:
        """Re-queue orphaned running jobs (lease expired, or at start-up: owned by a dead process
        of this host, or by this pid's previous life); fail those out of attempts."""
        now = time.time()
        orphans = []
        for r in self._exec("SELECT id, owner, lease_until, attempts FROM jobs WHERE state = 'running'"):
            owner = r["owner"] or ""
            host, _, pid = owner.rpartition(":")
            dead_here = startup and host == self.host and (pid == str(os.getpid()) or not _pid_alive(pid))
            if (r["lease_until"] or 0) < now or dead_here:
                orphans.append(r)
        for r in orphans:
            if r["attempts"] >= self.settings.job_max_attempts:
                problem = ProblemDetail(500, "Job failed", f"the job's worker stopped {r['attempts']} times")
                self._exec("UPDATE jobs SET state = 'failed', error = ?, owner = NULL, lease_until = NULL, finished_at = ?, updated_at = ?, expires_at = ? "
                           "WHERE id = ? AND state = 'running'", (json.dumps(_problem_json(problem)), now, now, now + self.settings.job_result_ttl_s, r["id"]))
            else:
                self._exec("UPDATE jobs SET state = 'queued', owner = NULL, lease_until = NULL, updated_at = ? WHERE id = ? AND state = 'running' AND owner IS ?",
                           (now, r["id"], r["owner"]))
        if orphans:
            log.warning("re-queued %d orphaned job(s)", len(orphans))
        return len(orphans)

    def expire(self) -> int:
        """Delete finished jobs (rows and result files) past their expiry."""
        rows = self._exec("DELETE FROM jobs WHERE expires_at IS NOT NULL AND expires_at < ? AND state IN ('succeeded', 'failed', 'cancelled') RETURNING id, format",
                          (time.time(),))
        for r in rows:
            self.result_path(r["id"], r["format"]).unlink(missing_ok=True)
        return len(rows)


class JobRunner:
    """Runs this store's queued jobs on the worker pool, ``job_concurrency`` at a time."""

    def __init__(self, store: SqliteJobStore, pool, metrics: Metrics | None = None):
        self.store, self.pool, self.metrics = store, pool, metrics
        self.settings = store.settings
        self._active: dict[str, asyncio.Task] = {}
        self._task: asyncio.Task | None = None
        self._wakeup = asyncio.Event()

    def notify(self) -> None:
        self._wakeup.set()

    async def start(self) -> None:
        self.store.recover(startup=True)
        self._task = asyncio.create_task(self._loop(), name="tryon-jobs")

    async def stop(self) -> None:
        """Running jobs go back to the queue (they restart on the next start)."""
        if self._task is not None:
            self._task.cancel()
        for task in list(self._active.values()):
            task.cancel()
        await asyncio.gather(*self._active.values(), return_exceptions=True)

    async def _loop(self) -> None:
        tick = 0
        last_error = ""
        while True:
            try:
                if tick % 20 == 0:
                    if self.store.degraded:
                        self.store.restore_reserve()
                    self.store.recover()
                    self.store.expire()
                tick += 1
                while len(self._active) < self.settings.job_concurrency and not self.store.degraded:  # a full disk: queued jobs wait
                    claimed = self.store.claim()
                    if claimed is None:
                        break
                    job_id, request_json, attempts = claimed
                    task = asyncio.create_task(self._run(job_id, request_json, attempts))
                    self._active[job_id] = task
                    task.add_done_callback(lambda _t, j=job_id: self._active.pop(j, None))
                if self.metrics is not None:
                    for state, n in self.store.counts().items():
                        self.metrics.jobs.labels(state).set(n)
                last_error = ""
            except Exception as exc:  # noqa: BLE001 - the loop must survive a failed poll (disk full, lock)
                if repr(exc) != last_error:  # once per distinct failure, not every poll
                    log.exception("job loop")
                last_error = repr(exc)
            self._wakeup.clear()
            try:
                await asyncio.wait_for(self._wakeup.wait(), self.settings.job_poll_s)
            except asyncio.TimeoutError:
                pass

    async def _run(self, job_id: str, request_json: str, attempts: int) -> None:
        from service.pool import WorkerCrashed
        from service.worker import JobOutcome

        store = self.store
        request = DrapeRequest.model_validate_json(request_json)
        path = store.result_path(job_id, request.format)

        async def heartbeat():
            while True:
                await asyncio.sleep(self.settings.job_lease_s / 3)
                try:
                    store.renew(job_id)
                except Exception:  # noqa: BLE001 - a failed renewal (full disk) is retried on the next beat
                    log.warning("job %s: lease renewal failed", job_id)

        def on_progress(done: int, total: int) -> bool:
            try:
                return not store.renew(job_id, done, total)
            except Exception:  # noqa: BLE001 - progress not recorded this time; the job goes on
                return False

        beat = asyncio.create_task(heartbeat())
        try:
            outcome = await self.pool.run_job(request, path, on_progress)
            if outcome is None:  # cancelled while running
                path.unlink(missing_ok=True)
            elif isinstance(outcome, JobOutcome):
                if not store.finish(job_id, "succeeded", result_bytes=outcome.result_bytes, headers=outcome.headers, frames=outcome.frames):
                    path.unlink(missing_ok=True)  # cancelled meanwhile
            else:
                if outcome.status == 507:  # the worker could not write the result: the disk is full
                    store.mark_full()
                store.finish(job_id, "failed", error=outcome)
        except WorkerCrashed as exc:
            log.error("job %s: %s", job_id, exc)
            if attempts >= self.settings.job_max_attempts:
                store.finish(job_id, "failed", error=ProblemDetail(500, "Job failed", "the job crashed its worker on every attempt"))
            else:
                store.release(job_id)
                self.notify()
        except ProblemException:  # the pool is shutting down
            store.release(job_id)
        except asyncio.CancelledError:
            store.release(job_id)
            raise
        except Exception as exc:  # noqa: BLE001
            log.exception("job %s", job_id)
            path.unlink(missing_ok=True)
            problem = storage_problem() if out_of_space(exc) else ProblemDetail(500, "Job failed", "the server failed to process the job")
            try:
                store.finish(job_id, "failed", error=problem)
            except Exception:  # noqa: BLE001 - not even the reserve helped: the lease runs out and recover() takes over
                log.exception("job %s: could not record its failure", job_id)
        finally:
            beat.cancel()


def _pid_alive(pid: str) -> bool:
    try:
        os.kill(int(pid), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


def _problem_json(p: ProblemDetail) -> dict:
    doc = {"type": "about:blank", "title": p.title, "status": p.status, "detail": p.detail}
    if p.errors:
        doc["errors"] = p.errors
    return doc


def _record(r: sqlite3.Row) -> JobRecord:
    return JobRecord(
        id=r["id"], state=r["state"], format=r["format"], frames_done=r["frames_done"], frames_total=r["frames_total"],
        attempts=r["attempts"], created_at=r["created_at"], updated_at=r["updated_at"], finished_at=r["finished_at"],
        expires_at=r["expires_at"], error=json.loads(r["error"]) if r["error"] else None, result_bytes=r["result_bytes"],
        headers=json.loads(r["headers"]) if r["headers"] else {},
    )
