"""Asynchronous jobs, Redis backend: an RQ queue, so that workers on several machines share jobs
(docker-compose: the ``api`` replicas enqueue, the ``worker`` service runs ``python -m service.worker``).

Why RQ: the work is a synchronous, CPU-bound Python function, which is exactly RQ's model (a
worker forks a work-horse per job: a crashing job kills the horse, not the worker, and RQ records
it and retries it per ``Retry``); job status, ``meta`` for progress, result and failure TTLs,
cancel and stop-job commands are built in, and Redis is its only dependency. arq is asyncio-first
(CPU work would block its loop), Celery brings a broker/backend/beat stack we do not need, and
Dramatiq has no job status or progress without extra middleware and its own result backend.

Results are files in ``<jobs_dir>/results`` (a volume shared by api and worker containers);
RQ keeps the job record (state, progress, error) with ``result_ttl = job_result_ttl_s``.

Abandoned jobs (worker and work-horse killed): RQ keeps a running job in its started registry
with a score of its last heartbeat + ``HEARTBEAT_S`` + 60 s and re-queues it (per its Retry) only
when a worker's maintenance, every 10 min by default, finds the score past. The API sweeps the
registry every ``sweep_every`` seconds with a cutoff that treats ``job_abandoned_s`` without a
heartbeat as abandoned, so such a job is queued again within ``job_abandoned_s`` + ``sweep_every``.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

from redis import Redis
from rq import Queue, Retry, Worker, get_current_job
from rq.command import send_stop_job_command
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job, JobStatus
from rq.registry import CanceledJobRegistry, FailedJobRegistry, FinishedJobRegistry, StartedJobRegistry

from service.config import Settings
from service.errors import ProblemDetail, problem_from_exception
from service.jobs import STATES, JobRecord, _problem_json, new_job_id, quota_problem
from service.schemas import DrapeRequest

log = logging.getLogger(__name__)

_RUNTIME = None  # loaded once by the worker process before it forks work-horses
HEARTBEAT_S = 5  # the RQ worker's job_monitoring_interval: it refreshes a running job's registry score this often
RQ_GRACE_S = 60  # RQ adds this to the heartbeat when it scores a running job (rq.worker: job_monitoring_interval + 60)

STATUS = {
    JobStatus.CREATED: "queued", JobStatus.QUEUED: "queued", JobStatus.DEFERRED: "queued", JobStatus.SCHEDULED: "queued",
    JobStatus.STARTED: "running", JobStatus.FINISHED: "succeeded", JobStatus.FAILED: "failed",
    JobStatus.STOPPED: "cancelled", JobStatus.CANCELED: "cancelled",
}


def perform_job(request_json: str, result_path: str) -> dict:
    """The RQ job function (runs in the work-horse): the result's size, headers and frames."""
    from service.runtime import Runtime
    from service.worker import execute_job

    global _RUNTIME
    if _RUNTIME is None:
        _RUNTIME = Runtime.load(Settings())
    job = get_current_job()

    def progress(done: int, total: int) -> bool:
        if job is not None:
            job.meta.update(frames_done=done, frames_total=total)
            job.save_meta()
        return False  # cancellation of a running job is RQ's stop-job command

    request = DrapeRequest.model_validate_json(request_json)
    try:
        outcome = execute_job(_RUNTIME, request, Path(result_path), progress)
    except Exception as exc:
        problem = problem_from_exception(exc)
        if problem.status < 500 and job is not None:  # an input problem fails the job for good: no retry
            job.meta["problem"] = _problem_json(problem)
            job.retries_left = 0
            job.save()
            raise JobInputError(problem.detail) from None
        raise
    return {"result_bytes": outcome.result_bytes, "headers": outcome.headers, "frames": outcome.frames}


class JobInputError(ValueError):
    """The job's request is invalid (its problem document is in job.meta['problem'])."""


class RedisJobStore:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.redis = Redis.from_url(settings.redis_url)
        self.queue = Queue(settings.redis_queue, connection=self.redis)
        self.results_dir = Path(settings.jobs_dir) / "results"
        self.results_dir.mkdir(parents=True, exist_ok=True)

    def close(self) -> None:
        self.redis.close()

    def ping(self) -> bool:
        try:
            return bool(self.redis.ping())
        except Exception:  # noqa: BLE001
            return False

    def result_path(self, job_id: str, fmt: str) -> Path:
        return self.results_dir / f"{job_id}.{fmt}"

    @property
    def sweep_every(self) -> float:
        return self.settings.job_abandoned_s / 4

    def sweep_abandoned(self) -> int:
        """Re-queue (or fail, when out of retries) running jobs without a heartbeat for
        ``job_abandoned_s``; the number found."""
        registry = StartedJobRegistry(queue=self.queue, connection=self.redis)
        cutoff = time.time() + HEARTBEAT_S + RQ_GRACE_S - self.settings.job_abandoned_s
        found = len(registry.get_expired_job_ids(cutoff))
        if found:
            registry.cleanup(timestamp=cutoff)
            log.warning("re-queued %d abandoned job(s) (no worker heartbeat for %.0f s)", found, self.settings.job_abandoned_s)
        return found

    def pending(self, client: str | None = None) -> int:
        """Queued + running jobs: of the queue, or of ``client`` (its set of job ids, pruned of
        those that finished or expired; at most ``job_max_pending_per_key`` members to check)."""
        if client is None:
            return int(self.queue.count + StartedJobRegistry(queue=self.queue, connection=self.redis).count)
        key = f"tryon:pending:{client}"
        ids = [i.decode() for i in self.redis.zrange(key, 0, -1)]
        jobs = Job.fetch_many(ids, connection=self.redis) if ids else []
        done = [i for i, j in zip(ids, jobs) if j is None or STATUS.get(j.get_status(refresh=False), "queued") not in ("queued", "running")]
        if done:
            self.redis.zrem(key, *done)
        return len(ids) - len(done)

    def create(self, request: DrapeRequest, client: str = "anonymous", request_json: str | None = None) -> JobRecord:
        """Queue a job within the quotas (429 past them). The check and the enqueue are two
        steps: concurrent API replicas may overshoot a quota by the requests in flight."""
        job_id = new_job_id()
        s = self.settings
        mine, everyone = self.pending(client), self.pending()
        if mine >= s.job_max_pending_per_key or everyone >= s.job_max_pending:
            raise quota_problem(mine, everyone, s).exception()
        key = f"tryon:pending:{client}"
        self.redis.zadd(key, {job_id: time.time()})
        self.redis.expire(key, int(s.job_timeout_s + s.job_result_ttl_s))
        self.queue.enqueue_call(
            perform_job, args=(request_json or request.model_dump_json(), str(self.result_path(job_id, request.format))), job_id=job_id,
            timeout=int(s.job_timeout_s), result_ttl=int(s.job_result_ttl_s), failure_ttl=int(s.job_result_ttl_s),
            retry=Retry(max=max(s.job_max_attempts - 1, 0)) if s.job_max_attempts > 1 else None,
            meta={"format": request.format, "frames_done": 0, "frames_total": None, "created_at": time.time()},
        )
        return self.get(job_id)

    def _job(self, job_id: str) -> Job | None:
        try:
            return Job.fetch(job_id, connection=self.redis)
        except NoSuchJobError:
            return None

    def get(self, job_id: str) -> JobRecord | None:
        job = self._job(job_id)
        if job is None:
            return None
        meta = job.get_meta(refresh=True)
        state = STATUS.get(job.get_status(refresh=True), "queued")
        error, result_bytes, headers, done = None, None, {}, meta.get("frames_done", 0)
        if state == "succeeded":
            value = job.return_value() or {}
            result_bytes, headers = value.get("result_bytes"), value.get("headers", {})
            done = value.get("frames", done)
        elif state == "failed":
            error = meta.get("problem") or _problem_json(ProblemDetail(500, "Job failed", "the server failed to process the job"))
        created = meta.get("created_at") or time.time()
        ended = job.ended_at.timestamp() if job.ended_at else None
        return JobRecord(
            id=job_id, state=state, format=meta.get("format", "glb"), frames_done=int(done or 0), frames_total=meta.get("frames_total"),
            attempts=0, created_at=created, updated_at=time.time(), finished_at=ended,
            expires_at=None if ended is None else ended + self.settings.job_result_ttl_s, error=error, result_bytes=result_bytes, headers=headers,
        )

    def cancel(self, job_id: str) -> JobRecord | None:
        record = self.get(job_id)
        if record is None:
            return None
        job = self._job(job_id)
        if record.state == "queued":
            job.cancel()
        elif record.state == "running":
            try:
                send_stop_job_command(self.redis, job_id)
            except InvalidJobOperation:
                pass
        else:
            job.delete()
            self.result_path(job_id, record.format).unlink(missing_ok=True)
        return record

    def counts(self) -> dict[str, int]:
        q, c = self.queue, self.redis
        got = {
            "queued": q.count,
            "running": StartedJobRegistry(queue=q, connection=c).count,
            "succeeded": FinishedJobRegistry(queue=q, connection=c).count,
            "failed": FailedJobRegistry(queue=q, connection=c).count,
            "cancelled": CanceledJobRegistry(queue=q, connection=c).count,
        }
        return {s: int(got.get(s, 0)) for s in STATES}


def run_rq_worker(settings: Settings, burst: bool = False) -> None:
    """Load the runtime, then work the queue (RQ forks a work-horse per job, which inherits it)."""
    from service.runtime import Runtime

    global _RUNTIME
    _RUNTIME = Runtime.load(settings)
    redis = Redis.from_url(settings.redis_url)
    worker = Worker([Queue(settings.redis_queue, connection=redis)], connection=redis, job_monitoring_interval=HEARTBEAT_S,
                    maintenance_interval=60)
    log.info("RQ worker on %s queue %s", settings.redis_url, settings.redis_queue)
    worker.work(burst=burst, logging_level=settings.log_level.upper())
