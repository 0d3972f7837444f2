"""Asynchronous drapes: POST /v1/jobs (202 + Location), GET status/progress, GET result, DELETE."""
from __future__ import annotations

from fastapi import APIRouter, Path, Request
from fastapi.responses import FileResponse, JSONResponse, Response

from service.auth import client_id
from service.errors import ProblemException
from service.jobs import MEDIA_TYPES, JobRecord
from service.parsing import request_body_openapi
from service.schemas import BINARY as _BINARY, DRAPE_EXAMPLE, JobProgress, JobResponse
from service.runtime import RequestLimits

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])
JOB_ID_PATTERN = r"^[0-9a-f]{32}$"
_PROBLEM = {"content": {"application/problem+json": {}}}
_NOT_FOUND = {404: {"description": "no such job (or it expired)", **_PROBLEM}}


def _store(request: Request):
    store = request.app.state.job_store
    if store is None:
        raise ProblemException(503, "Jobs disabled", "this deployment runs no job backend", headers={"Retry-After": "60"})
    return store


def _response(record: JobRecord) -> JobResponse:
    total = record.frames_total
    return JobResponse(
        id=record.id, state=record.state, format=record.format,
        progress=JobProgress(frames_done=record.frames_done, frames_total=total, fraction=(record.frames_done / total) if total else 0.0),
        created_at=record.created_at, finished_at=record.finished_at, expires_at=record.expires_at,
        result_url=f"/v1/jobs/{record.id}/result" if record.state == "succeeded" else None,
        result_bytes=record.result_bytes, error=record.error,
    )


def _get(request: Request, job_id: str) -> JobRecord:
    record = _store(request).get(job_id)
    if record is None:
        raise ProblemException(404, "Not found", f"no job {job_id!r} (unknown, deleted or expired)")
    return record


@router.post(
    "",
    status_code=202,
    response_model=JobResponse,
    openapi_extra=request_body_openapi(DRAPE_EXAMPLE),
    responses={
        202: {"description": "accepted: poll the Location", "headers": {"Location": {"schema": {"type": "string"}, "description": "the job's URL"}}},
        400: {"description": "the body is not parseable JSON", **_PROBLEM},
        413: {"description": "request body too large", **_PROBLEM},
        415: {"description": "the body is not application/json", **_PROBLEM},
        429: {"description": "too many unfinished jobs, for this API key or in all: retry after the Retry-After seconds", **_PROBLEM},
        422: {"description": "invalid request: the problem names the field", **_PROBLEM},
        503: {"description": "jobs are disabled or the queue is unavailable", **_PROBLEM},
        507: {"description": "the job store's disk is full: retry after the Retry-After seconds", **_PROBLEM},
    },
)
async def post_job(request: Request):
    """The body of POST /v1/drape (a ``DrapeRequest``), with the job limits (frames, vertices,
    request size); the result is kept for the configured time."""
    store = _store(request)
    drape_request, request_json = await request.app.state.parser.parse(request)
    request.app.state.runtime.check_request(drape_request, RequestLimits.job(request.app.state.runtime.settings))
    try:
        client = client_id(request.headers, request.app.state.settings.api_key_header) if request.app.state.auth_on else "anonymous"
        record = store.create(drape_request, client, request_json)
    except ProblemException:
        raise
    except Exception as exc:  # noqa: BLE001 - the queue (Redis, disk) is unavailable: nothing was accepted
        raise ProblemException(503, "Queue unavailable", "the job could not be stored; retry", headers={"Retry-After": "5"}) from exc
    runner = request.app.state.job_runner
    if runner is not None:
        runner.notify()
    location = f"/v1/jobs/{record.id}"
    return JSONResponse(_response(record).model_dump(mode="json"), status_code=202, headers={"Location": location})


@router.get("/{job_id}", response_model=JobResponse, responses=_NOT_FOUND)
def get_job(request: Request, job_id: str = Path(pattern=JOB_ID_PATTERN)) -> JobResponse:
    return _response(_get(request, job_id))


@router.get(
    "/{job_id}/result",
    response_class=Response,
    responses={
        200: {"description": "the job's output (glb or npz, as POST /v1/drape)", "content": {"model/gltf-binary": _BINARY, "application/x-npz": _BINARY}},
        409: {"description": "the job has no result (not finished, failed or cancelled)", **_PROBLEM},
        **_NOT_FOUND,
    },
)
def get_job_result(request: Request, job_id: str = Path(pattern=JOB_ID_PATTERN)):
    record = _get(request, job_id)
    if record.state in ("queued", "running"):
        raise ProblemException(409, "Not finished", f"the job is {record.state} ({record.frames_done} frames done)", headers={"Retry-After": "2"})
    if record.state != "succeeded":
        raise ProblemException(409, "No result", f"the job {record.state}")
    path = _store(request).result_path(job_id, record.format)
    if not path.is_file():
        raise ProblemException(404, "Not found", "the result expired")
    headers = {k: v for k, v in record.headers.items() if k in ("X-Frames",)}
    return FileResponse(path, media_type=MEDIA_TYPES[record.format], headers=headers)


@router.delete("/{job_id}", status_code=204, response_class=Response, responses={204: {"description": "cancelled (queued or running) or deleted (finished)"}, **_NOT_FOUND,
                                                                             503: {"description": "the store cannot be written now: retry", **_PROBLEM}})
def delete_job(request: Request, job_id: str = Path(pattern=JOB_ID_PATTERN)):
    try:
        cancelled = _store(request).cancel(job_id)
    except ProblemException:
        raise
    except Exception as exc:  # noqa: BLE001 - the store cannot write (a full disk past its reserve): retry, not 500
        raise ProblemException(503, "Store unavailable", "the job could not be changed; retry", headers={"Retry-After": "30"}) from exc
    if cancelled is None:
        raise ProblemException(404, "Not found", f"no job {job_id!r}")
    return Response(status_code=204)
