"""POST /v1/drape: synchronous drape of garments on a body following a motion."""
from __future__ import annotations

from fastapi import APIRouter, Body, Request
from fastapi.responses import Response

from service.schemas import DRAPE_EXAMPLE, DrapeRequest

router = APIRouter(prefix="/v1", tags=["drape"])

MEDIA_TYPES = {"glb": "model/gltf-binary", "npz": "application/x-npz"}
_PROBLEM = {"content": {"application/problem+json": {}}}


@router.post(
    "/drape",
    response_class=Response,
    responses={
        200: {
            "description": "the animated garments (and body): glb (Y-up, metres, morph-target animation) or npz (float32 arrays, Z-up)",
            "content": {"model/gltf-binary": {}, "application/x-npz": {}},
        },
        400: {"description": "the body is not parseable JSON", **_PROBLEM},
        413: {"description": "request body too large", **_PROBLEM},
        422: {"description": "invalid request: the problem names the field", **_PROBLEM},
        503: {"description": "busy: retry after the Retry-After seconds", **_PROBLEM},
    },
)
async def post_drape(
    request: Request,
    drape_request: DrapeRequest = Body(openapi_examples={"walk_tshirt": {"summary": "neutral body, walk clip, T-shirt", "value": DRAPE_EXAMPLE}}),
) -> Response:
    runtime = request.app.state.runtime
    result = await runtime.drape(drape_request)
    return Response(content=result.payload, media_type=MEDIA_TYPES[drape_request.format], headers=result.headers)
