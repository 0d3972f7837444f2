"""Inference workers: the process entry point of the pool's workers, and ``python -m service.worker``,
the RQ worker of the Redis job backend (docker-compose's ``worker`` service).

A pool worker loads the runtime once, then serves messages from its pipe:
  ("drape", [DrapeRequest, ...])            -> ("done", [DrapeOutput | ProblemDetail, ...])
  ("job", DrapeRequest, result_path)        -> ("progress", done, total)* then ("done", JobOutcome | ProblemDetail | None)
the parent answers each progress message with True to cancel the job. ``None`` asks the worker to
stop; when it arrives in place of a progress answer (the pool stopping while a job runs), the
worker exits at once without reporting the job, whose lease then expires: it is run again after
the restart, not lost (and no answer is left in the pipe to be misread as a message).
"""
from __future__ import annotations

import argparse
import logging
import os
import select
import threading
import time
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass
class JobOutcome:
    """A finished job: the result is in ``result_path`` (written atomically)."""

    headers: dict[str, str]
    result_bytes: int
    frames: int
    timings_ms: dict[str, float]


def write_atomic(path: Path, payload: bytes) -> None:
    """Write then rename, fsynced: a crash never leaves a partial result under ``path``, and a
    failed write leaves no temporary file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:  # a full disk (ENOSPC) or a kill: no partial file is left behind
        tmp.unlink(missing_ok=True)
        raise


def execute_job(runtime, request, result_path: Path, progress) -> "JobOutcome | None":
    """Run one job and store its result; None when ``progress`` asked to cancel."""
    out = runtime.run_job(request, progress)
    if out is None:
        return None
    write_atomic(Path(result_path), out.payload)
    return JobOutcome(headers=out.headers, result_bytes=len(out.payload), frames=int(out.headers.get("X-Frames", 0)), timings_ms=out.timings_ms)


class _Stop(Exception):
    """The parent asked the worker to stop while a job was running."""


def exit_with(pid: int, poll_s: float = 0.5) -> threading.Thread:
    """Exit this process as soon as process ``pid`` (the API that owns the pool) is gone, even
    while the main thread is busy with a long drape: a daemon thread waits on a pidfd (readable
    when ``pid`` exits; no pid-reuse race), or polls ``kill(pid, 0)`` where pidfds are missing.
    Pool workers are children of the forkserver, not of the API, so the pipe's EOF (seen only
    between messages) and PR_SET_PDEATHSIG (the forkserver's death) do not cover it."""
    def watch():
        try:
            fd = os.pidfd_open(pid)
        except (AttributeError, OSError):
            fd = None
        if fd is not None:
            select.select([fd], [], [])
        else:
            while True:
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    break
                except PermissionError:
                    pass
                time.sleep(poll_s)
        os._exit(0)

    thread = threading.Thread(target=watch, name="tryon-parent-watch", daemon=True)
    thread.start()
    return thread


def serve_pipe(conn, settings, parent_pid: int | None = None) -> None:
    """Pool worker process main loop (spawned by service.pool.ProcessWorker); the worker exits
    when ``parent_pid`` (the API process) dies, busy or not."""
    from service.errors import problem_from_exception
    from service.logs import configure_logging
    from service.runtime import Runtime

    if parent_pid is not None:
        exit_with(parent_pid)
    configure_logging(settings.log_level, settings.log_json)
    runtime = Runtime.load(settings)
    conn.send(("ready", os.getpid()))
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):  # the parent is gone
            return
        if message is None:
            return
        if not isinstance(message, tuple) or not message:
            log.warning("worker: ignored an unexpected message %r", type(message).__name__)
            continue
        kind = message[0]
        if kind == "drape":
            conn.send(("done", runtime.run_batch(message[1])))
        elif kind == "body":
            conn.send(("done", runtime.bodies.run(message[1], message[2])))
        elif kind == "job":
            def progress(done: int, total: int) -> bool:
                conn.send(("progress", done, total))
                reply = conn.recv()
                if reply is None:  # the pool is stopping: leave the job to its lease
                    raise _Stop
                return bool(reply)

            try:
                conn.send(("done", execute_job(runtime, message[1], message[2], progress)))
            except _Stop:
                log.info("worker: stopping during a job; it will be run again after the restart")
                return
            except Exception as exc:  # noqa: BLE001 - the job's problem, the worker lives on
                problem = problem_from_exception(exc)
                if problem.status >= 500:
                    log.error("job failed", exc_info=exc)
                conn.send(("done", problem))


def main(argv: list[str] | None = None) -> None:
    """``python -m service.worker``: an RQ worker for the Redis job backend. The runtime is loaded
    once here; RQ forks a work-horse per job, which inherits it (copy-on-write)."""
    from service.config import Settings
    from service.jobs_redis import run_rq_worker
    from service.logs import configure_logging

    defaults = Settings()
    parser = argparse.ArgumentParser(prog="python -m service.worker", description="Run a job worker on the Redis queue.")
    parser.add_argument("--redis-url", default=defaults.redis_url, help="env TRYON_REDIS_URL")
    parser.add_argument("--queue", default=defaults.redis_queue, help="env TRYON_REDIS_QUEUE")
    parser.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    args = parser.parse_args(argv)
    settings = defaults.model_copy(update={"redis_url": args.redis_url, "redis_queue": args.queue})
    configure_logging(settings.log_level, settings.log_json)
    run_rq_worker(settings, burst=args.burst)


if __name__ == "__main__":
    main()
