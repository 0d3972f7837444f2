"""GET /metrics: Prometheus text exposition."""
from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=Response, responses={200: {"content": {"text/plain": {}}, "description": "Prometheus metrics"}})
def metrics(request: Request) -> Response:
    state = request.app.state
    if state.job_store is not None:
        try:
            for job_state, n in state.job_store.counts().items():
                state.metrics.jobs.labels(job_state).set(n)
        except Exception:  # noqa: BLE001 - the queue is down: the other metrics still answer
            pass
    if state.pool is not None:
        state.metrics.queue_depth.set(state.pool.queue_depth)
    return Response(generate_latest(state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
