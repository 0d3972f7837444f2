"""POST /v1/drape: synchronous drape of garments on a body following a motion."""
from __future__ import annotations

from fastapi import APIRouter, Body, Request
from fastapi.responses import Response

from service.cache import etag_matches, etag_of, request_key, wildcard
from service.errors import ProblemException
from service.schemas import DRAPE_EXAMPLE, DrapeRequest

router = APIRouter(prefix="/v1", tags=["drape"])

MEDIA_TYPES = {"glb": "model/gltf-binary", "npz": "application/x-npz"}
_PROBLEM = {"content": {"application/problem+json": {}}}


@router.post(
    "/drape",
    response_class=Response,
    responses={
        200: {
            "description": "the animated garments (and body): glb (Y-up, metres, morph-target animation) or npz (float32 arrays, Z-up). "
                           "ETag: a weak tag of the request, the model versions and the garments' default methods (content-addressed).",
            "content": {"model/gltf-binary": {}, "application/x-npz": {}},
            "headers": {"ETag": {"schema": {"type": "string"}}, "X-Cache": {"schema": {"type": "string", "enum": ["hit", "miss", "coalesced"]}}},
        },
        304: {"description": "If-None-Match names this request's ETag: the client's copy is current (the drape is a safe "
                             "computation, so a matching tag is answered as a GET would be)"},
        400: {"description": "the body is not parseable JSON", **_PROBLEM},
        412: {"description": "If-None-Match: * (a drape always has a representation)", **_PROBLEM},
        413: {"description": "request body too large", **_PROBLEM},
        415: {"description": "the body is not application/json", **_PROBLEM},
        422: {"description": "invalid request: the problem names the field", **_PROBLEM},
        503: {"description": "busy (queue full) or shutting down: retry after the Retry-After seconds", **_PROBLEM},
        504: {"description": "the drape did not finish within the request deadline", **_PROBLEM},
    },
)
async def post_drape(
    request: Request,
    drape_request: DrapeRequest = Body(openapi_examples={"walk_tshirt": {"summary": "neutral body, walk clip, T-shirt", "value": DRAPE_EXAMPLE}}),
) -> Response:
    state = request.app.state
    key = request_key(drape_request, request.app.version, state.runtime.defaults, state.runtime.assets.combined)
    etag = etag_of(key)
    if wildcard(request.headers.get("if-none-match")):
        raise ProblemException(412, "Precondition failed", "If-None-Match: * cannot hold: every valid drape request has a result")
    if etag_matches(request.headers.get("if-none-match"), key):
        state.metrics.cache.labels("not_modified").inc()
        return Response(status_code=304, headers={"ETag": etag})
    result, how = await state.cache.get_or_compute(key, lambda: state.pool.drape(drape_request))
    state.metrics.cache.labels(how).inc()
    headers = {**result.headers, "ETag": etag, "X-Cache": how}
    return Response(content=result.payload, media_type=MEDIA_TYPES[drape_request.format], headers=headers)
