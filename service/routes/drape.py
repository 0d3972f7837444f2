"""POST /v1/drape: synchronous drape of garments on a body following a motion."""
from __future__ import annotations

import asyncio

from fastapi import APIRouter, Request
from fastapi.responses import Response

from service.cache import etag_matches, etag_of, wildcard
from service.errors import ProblemException
from service.http_rules import GZIP_MIN_BYTES, accepts_gzip, gzip_mesh
from service.jobs import MEDIA_TYPES
from service.parsing import KeyContext, accepted_formats, not_acceptable, request_body_openapi
from service.schemas import BINARY as _BINARY, DRAPE_EXAMPLE

router = APIRouter(prefix="/v1", tags=["drape"])

_PROBLEM = {"content": {"application/problem+json": {}}}


@router.post(
    "/drape",
    response_class=Response,
    openapi_extra=request_body_openapi(DRAPE_EXAMPLE),
    responses={
        200: {
            "description": "the animated garments (and body): glb (Y-up, metres, morph-target animation) or npz (float32 arrays, Z-up). "
                           "ETag: a weak tag of the request, the model versions and the garments' default methods (content-addressed).",
            "content": {"model/gltf-binary": _BINARY, "application/x-npz": _BINARY},
            "headers": {"ETag": {"schema": {"type": "string"}}, "X-Cache": {"schema": {"type": "string", "enum": ["hit", "miss", "coalesced"]}}},
        },
        304: {"description": "If-None-Match names this request's ETag: the client's copy is current (the drape is a safe "
                             "computation, so a matching tag is answered as a GET would be)"},
        400: {"description": "the body is not parseable JSON", **_PROBLEM},
        406: {"description": "the Accept header allows neither model/gltf-binary nor application/x-npz, or refuses the body's format", **_PROBLEM},
        412: {"description": "If-None-Match: * (a drape always has a representation)", **_PROBLEM},
        413: {"description": "request body too large", **_PROBLEM},
        415: {"description": "the body is not application/json", **_PROBLEM},
        422: {"description": "invalid request: the problem names the field; also a request estimated to take longer "
                             "than the request deadline (use POST /v1/jobs)", **_PROBLEM},
        503: {"description": "busy (queue full, checked before the body is read) or shutting down: retry after the "
                             "Retry-After seconds", **_PROBLEM},
        504: {"description": "the drape did not finish within the request deadline", **_PROBLEM},
    },
)
async def post_drape(request: Request) -> Response:
    """The body is a ``DrapeRequest`` (see the schema). The output format is the body's
    ``format``, else the one the ``Accept`` header prefers (``model/gltf-binary`` or
    ``application/x-npz``; 406 when it allows neither or refuses the body's). Admission happens
    before the body is read (503 when the queue is full) and again once it is validated (422 when
    the drape is estimated to outlast the deadline); large bodies are validated off the event loop."""
    state = request.app.state
    accept = accepted_formats(request.headers.get("accept"))
    if accept == ():
        raise not_acceptable(f"Accept: {request.headers.get('accept', '')[:100]!r} allows neither")
    state.pool.admit()
    runtime = state.runtime
    drape_request, key = await state.parser.parse(request, KeyContext(request.app.version, runtime.defaults, runtime.assets.combined, accept))
    etag = etag_of(key)
    if wildcard(request.headers.get("if-none-match")):
        raise ProblemException(412, "Precondition failed", "If-None-Match: * cannot hold: every valid drape request has a result")
    if etag_matches(request.headers.get("if-none-match"), key):
        state.metrics.cache.labels("not_modified").inc()
        return Response(status_code=304, headers={"ETag": etag, "Vary": "Accept"})
    if state.cache.get(key) is None:
        runtime.check_request(drape_request)  # the cheap 422s first (unknown ids, the frame limit), then the cost
        state.pool.admit_cost(runtime.output_frames(drape_request), len(drape_request.garments))
    result, how = await state.cache.get_or_compute(key, lambda: state.pool.drape(drape_request))
    state.metrics.cache.labels(how).inc()
    headers = {**result.headers, "ETag": etag, "X-Cache": how, "Vary": "Accept, Accept-Encoding"}
    payload = result.payload
    if accepts_gzip(request.headers.get("accept-encoding")) and len(payload) >= GZIP_MIN_BYTES:
        # gzip here, on a thread (ISA-L lets go of the GIL), not in GZipMiddleware on the event loop:
        # a 22 MB glb takes ~40 ms (the middleware passes answers that already have an encoding)
        payload = await asyncio.to_thread(gzip_mesh, payload)
        headers["Content-Encoding"] = "gzip"
    return Response(content=payload, media_type=MEDIA_TYPES[drape_request.format], headers=headers)
