"""Liveness and readiness."""
from __future__ import annotations

from fastapi import APIRouter, Request

from service.errors import ProblemException
from service.schemas import HealthResponse, ReadyResponse, ReadyWorker

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=HealthResponse)
def healthz() -> HealthResponse:
    """The process is up."""
    return HealthResponse(status="ok")


@router.get("/readyz", response_model=ReadyResponse, responses={503: {"description": "not ready", "content": {"application/problem+json": {}}}})
def readyz(request: Request) -> ReadyResponse:
    """Models and assets are loaded (warm) in the workers, at least one worker is alive, the
    pool takes requests and the job backend answers."""
    state = request.app.state
    runtime, pool = state.runtime, state.pool
    if runtime is None or pool is None:
        raise ProblemException(503, "Not ready", "models are still loading", headers={"Retry-After": "1"})
    if not pool.ready:
        raise ProblemException(503, "Not ready", "no inference worker is alive (or the service is shutting down)", headers={"Retry-After": "1"})
    ping = getattr(state.job_store, "ping", None)
    if ping is not None and not ping():
        detail = "the job store's disk is full" if getattr(state.job_store, "degraded", False) else "the job queue (Redis) does not answer"
        raise ProblemException(503, "Not ready", detail, headers={"Retry-After": "5"})
    return ReadyResponse(
        status="ready", garments=len(runtime.catalog.ids()), motions=len(runtime.clips.ids()),
        workers=[ReadyWorker(**w) for w in pool.worker_health()], queue_depth=pool.queue_depth,
        jobs_backend=state.settings.jobs_backend,
    )
