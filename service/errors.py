"""RFC 9457 problem details (``application/problem+json``), in one place.

Every error the service returns goes through here: validation errors name the request field
(a JSON pointer in ``errors[].pointer``), and no stack trace ever reaches a client.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
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


@dataclass(frozen=True)
class ProblemDetail:
    """A problem document's fields: picklable, so that a worker process can send it back."""

    status: int
    title: str
    detail: str
    errors: list[dict] = field(default_factory=list)
    headers: dict[str, str] = field(default_factory=dict)

    def exception(self) -> "ProblemException":
        return ProblemException(self.status, self.title, self.detail, list(self.errors), dict(self.headers))


def problem_from_exception(exc: BaseException) -> ProblemDetail:
    """The problem document for an exception raised while serving a request (one mapping for
    the app's handlers and the worker processes); unknown exceptions become a bare 500."""
    if isinstance(exc, ProblemException):
        return ProblemDetail(exc.status, exc.title, exc.detail, exc.errors, exc.headers)
    if isinstance(exc, UnknownAssetError):
        pointer = {"motion.clip": "/body/motion/clip"}.get(exc.field, exc.field)
        return ProblemDetail(422, "Unknown asset", str(exc), [{"pointer": pointer, "detail": exc.detail}])
    if isinstance(exc, MotionFormatError):
        return ProblemDetail(422, "Malformed motion", str(exc)[:1000], [{"pointer": "/body/motion", "detail": str(exc)[:1000]}])
    if isinstance(exc, InferenceInputError):
        return ProblemDetail(422, "Invalid input", str(exc), [{"pointer": exc.field, "detail": exc.detail}])
    return ProblemDetail(500, "Internal error", "the server failed to process the request")


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

    @app.exception_handler(InferenceInputError)
    async def _inference_input(request: Request, exc: InferenceInputError):
        p = problem_from_exception(exc)
        return problem_response(p.status, p.title, p.detail, request.url.path, p.errors, p.headers)

    @app.exception_handler(ProblemException)
    async def _problem(request: Request, exc: ProblemException):
        return problem_response(exc.status, exc.title, exc.detail, request.url.path, exc.errors, exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        title = {400: "Bad request", 404: "Not found", 405: "Method not allowed", 413: "Request too large"}.get(exc.status_code, "HTTP error")
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:  # every method of every route on this path (Starlette names only the first route's)
            headers["Allow"] = ", ".join(_allowed_methods(request))
        return problem_response(exc.status_code, title, str(exc.detail), request.url.path, headers=headers or None)

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):
        log.exception("unhandled error on %s", request.url.path)
        return problem_response(500, "Internal error", "the server failed to process the request", request.url.path)


def _allowed_methods(request: Request) -> list[str]:
    from starlette.routing import Match

    methods: set[str] = set()
    for route in request.app.routes:
        match, _ = route.matches({**request.scope, "method": "GET"})
        if match != Match.NONE and getattr(route, "methods", None):
            methods |= set(route.methods)
    return sorted(methods)
