"""Bundled motion clips."""
from __future__ import annotations

from fastapi import APIRouter, Request

from service.schemas import MotionListResponse, MotionSummary

router = APIRouter(prefix="/v1", tags=["motions"])

CMU_ACKNOWLEDGEMENT = (
    "The data used in this project was obtained from mocap.cs.cmu.edu. "
    "The database was created with funding from NSF EIA-0196217."
)


@router.get("/motions", response_model=MotionListResponse)
def list_motions(request: Request) -> MotionListResponse:
    clips = request.app.state.runtime.clips
    return MotionListResponse(
        motions=[MotionSummary(**clips.summary(i)) for i in clips.ids()],
        acknowledgement=CMU_ACKNOWLEDGEMENT,
    )
