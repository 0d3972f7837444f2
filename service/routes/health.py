"""Liveness and readiness."""
from __future__ import annotations

from fastapi import APIRouter, Request

from service.errors import ProblemException
from service.schemas import HealthResponse, ReadyResponse

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=HealthResponse)
def healthz() -> HealthResponse:
    """The process is up."""
    return HealthResponse(status="ok")


@router.get("/readyz", response_model=ReadyResponse, responses={503: {"description": "not ready", "content": {"application/problem+json": {}}}})
def readyz(request: Request) -> ReadyResponse:
    """Models and assets are loaded and the service takes requests."""
    runtime = request.app.state.runtime
    if runtime is None:
        raise ProblemException(503, "Not ready", "assets are still loading", headers={"Retry-After": "1"})
    return ReadyResponse(status="ready", garments=len(runtime.catalog.ids()), motions=len(runtime.clips.ids()))
