"""RFC 9457 problem details (``application/problem+json``), in one place.

Every error the service returns goes through here: validation errors name the request field
(a JSON pointer in ``errors[].pointer``), and no stack trace ever reaches a client.
"""
from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from inference.errors import InferenceInputError, UnknownAssetError
from inference.motion.skeleton import MotionFormatError

log = logging.getLogger(__name__)

PROBLEM_JSON = "application/problem+json"


class ProblemException(Exception):
    """Raised at the edge (routes) to answer with a problem document."""

    def __init__(self, status: int, title: str, detail: str, errors: list[dict] | None = None, headers: dict | None = None):
        super().__init__(detail)
        self.status, self.title, self.detail = status, title, detail
        self.errors = errors or []
        self.headers = headers or {}


def problem_response(status: int, title: str, detail: str, instance: str = "", errors: list[dict] | None = None, headers: dict | None = None) -> JSONResponse:
    body: dict[str, Any] = {"type": "about:blank", "title": title, "status": status, "detail": detail}
    if instance:
        body["instance"] = instance
    if errors:
        body["errors"] = errors
    return JSONResponse(body, status_code=status, media_type=PROBLEM_JSON, headers=headers)


def _pointer(loc: tuple | list) -> str:
    """A pydantic error location as a JSON pointer into the request (``/body/garments/0/id``)."""
    return "/" + "/".join(str(p) for p in loc)


def _jsonable(value: Any) -> Any:
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)[:200]


def install_problem_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = [
            {"pointer": _pointer(e.get("loc", ())), "detail": str(e.get("msg", ""))[:500], "type": _jsonable(e.get("type"))}
            for e in exc.errors()[:50]
        ]
        first = errors[0]["pointer"] if errors else "request"
        return problem_response(422, "Invalid request", f"{len(exc.errors())} invalid field(s), first: {first}", request.url.path, errors)

    @app.exception_handler(UnknownAssetError)
    async def _unknown(request: Request, exc: UnknownAssetError):
        pointer = {"motion.clip": "/body/motion/clip"}.get(exc.field, exc.field)
        return problem_response(422, "Unknown asset", str(exc), request.url.path, [{"pointer": pointer, "detail": exc.detail}])

    @app.exception_handler(InferenceInputError)
    async def _inference_input(request: Request, exc: InferenceInputError):
        return problem_response(422, "Invalid input", str(exc), request.url.path, [{"pointer": exc.field, "detail": exc.detail}])

    @app.exception_handler(MotionFormatError)
    async def _motion_format(request: Request, exc: MotionFormatError):
        return problem_response(422, "Malformed motion", str(exc)[:1000], request.url.path, [{"pointer": "/body/motion", "detail": str(exc)[:1000]}])

    @app.exception_handler(ProblemException)
    async def _problem(request: Request, exc: ProblemException):
        return problem_response(exc.status, exc.title, exc.detail, request.url.path, exc.errors, exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        title = {400: "Bad request", 404: "Not found", 405: "Method not allowed", 413: "Request too large"}.get(exc.status_code, "HTTP error")
        return problem_response(exc.status_code, title, str(exc.detail), request.url.path, headers=getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):
        log.exception("unhandled error on %s", request.url.path)
        return problem_response(500, "Internal error", "the server failed to process the request", request.url.path)
