"""RFC 9457 problem details (``application/problem+json``), in one place.

Every error the service returns goes through here: validation errors name the request field
(an RFC 6901 JSON pointer into the request document in ``errors[].pointer``, ``""`` for the
whole document; a path, query or header parameter by name in ``errors[].parameter``), and no
stack trace ever reaches a client. Unparseable JSON is 400 (RFC 9110), a body that is not JSON
415; everything that parses but is invalid is 422.
"""
from __future__ import annotations

import errno
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
        pointer = {"motion.clip": "/motion/clip"}.get(exc.field, exc.field)
        return ProblemDetail(422, "Unknown asset", str(exc), [{"pointer": pointer, "detail": exc.detail}])
    if isinstance(exc, MotionFormatError):
        return ProblemDetail(422, "Malformed motion", str(exc)[:1000], [{"pointer": "/motion", "detail": str(exc)[:1000]}])
    if isinstance(exc, InferenceInputError):
        return ProblemDetail(422, "Invalid input", str(exc), [{"pointer": exc.field, "detail": exc.detail}])
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return ProblemDetail(507, "Insufficient storage", "the result could not be stored: the disk is full", headers={"Retry-After": "60"})
    return ProblemDetail(500, "Internal error", "the server failed to process the request")


def problem_response(status: int, title: str, detail: str, instance: str = "", errors: list[dict] | None = None, headers: dict | None = None) -> JSONResponse:
    body: dict[str, Any] = {"type": "about:blank", "title": title, "status": status, "detail": detail}
    if instance:
        body["instance"] = instance
    if errors:
        body["errors"] = errors
    return JSONResponse(body, status_code=status, media_type=PROBLEM_JSON, headers=headers)


MOTION_TAGS = ("clip", "poses", "bvh", "asf_amc")  # the values of the motion discriminator, ``type`` (service/schemas.py)


def _escape(token) -> str:
    return str(token).replace("~", "~0").replace("/", "~1")


def field_of(loc: tuple | list) -> dict[str, str]:
    """Where a FastAPI validation error lies: ``{"pointer": ...}``, an RFC 6901 pointer into the
    request body (loc ``("body", "garments", 0, "id")`` -> ``/garments/0/id``; pydantic's
    union-member tag after ``motion``, ``clip`` in ``("body", "motion", "clip", "start_s")``, is not
    part of the document and is dropped), or ``{"parameter": name, "in": "path" | "query" | "header"}``."""
    loc = list(loc)
    if loc and loc[0] == "body":
        path = loc[1:]
        if len(path) >= 2 and path[0] == "motion" and path[1] in MOTION_TAGS:
            del path[1]
        return {"pointer": "".join("/" + _escape(p) for p in path)}
    if loc and loc[0] in ("path", "query", "header", "cookie"):
        return {"parameter": ".".join(str(p) for p in loc[1:]), "in": loc[0]}
    return {"pointer": "".join("/" + _escape(p) for p in loc)}


def _jsonable(value: Any) -> Any:
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)[:200]


def install_problem_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        raw = exc.errors()
        if any(e.get("type") == "json_invalid" for e in raw):
            where = next(e for e in raw if e.get("type") == "json_invalid")
            position = where.get("loc", ("body", "?"))[-1]
            detail = f"the body is not valid JSON ({where.get('ctx', {}).get('error', 'parse error')} at character {position})"
            return problem_response(400, "Malformed JSON", detail[:500], request.url.path)
        errors = [
            {**field_of(e.get("loc", ())), "detail": str(e.get("msg", ""))[:500], "type": _jsonable(e.get("type"))}
            for e in raw[:50]
        ]
        first = (errors[0].get("pointer", errors[0].get("parameter")) or "(the whole request)") if errors else "request"
        return problem_response(422, "Invalid request", f"{len(raw)} invalid field(s), first: {first}", request.url.path, errors)

    @app.exception_handler(InferenceInputError)
    async def _inference_input(request: Request, exc: InferenceInputError):
        p = problem_from_exception(exc)
        return problem_response(p.status, p.title, p.detail, request.url.path, p.errors, p.headers)

    @app.exception_handler(ProblemException)
    async def _problem(request: Request, exc: ProblemException):
        return problem_response(exc.status, exc.title, exc.detail, request.url.path, exc.errors, exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        title = {400: "Bad request", 404: "Not found", 405: "Method not allowed", 412: "Precondition failed", 413: "Request too large",
                 415: "Unsupported media type"}.get(exc.status_code, "HTTP error")
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
