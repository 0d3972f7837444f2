"""Request bodies of POST /v1/drape and /v1/jobs, validated without stalling the event loop.

pydantic-core validates in Rust holding the GIL, so a thread does not help: an 8 MB ``poses``
body takes ~0.5 s to validate and ~0.6 s more to key (canonical JSON for the cache and ETag),
during which every other request, ``/healthz`` included, waits. Bodies up to
``INLINE_BYTES`` are validated inline (well under a millisecond); larger ones are validated and
keyed in a separate process, and only the result is unpickled here (~0.2 s for 7 MB).

Invalid bodies raise FastAPI's ``RequestValidationError`` with ``("body", ...)`` locations, as
FastAPI's own body parsing does, so the problem documents (service/errors.py) are the same.
"""
from __future__ import annotations

import asyncio
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from inference.defaults import DefaultMethods
from service.cache import request_key
from service.errors import ProblemException
from service.jobs import MEDIA_TYPES
from service.schemas import DrapeRequest

INLINE_BYTES = 256 * 1024


@dataclass(frozen=True)
class KeyContext:
    """What a request's cache key depends on besides the request (service.cache.request_key),
    and the formats the client accepts (``accepted_formats``; None: any)."""

    api_version: str
    defaults: DefaultMethods
    assets: str
    accept: tuple[str, ...] | None = None


MEDIA_FORMATS = {media: fmt for fmt, media in MEDIA_TYPES.items()}  # media type -> the request's format


def accepted_formats(accept: str | None) -> tuple[str, ...] | None:
    """The output formats an ``Accept`` header allows, most preferred first (RFC 9110 §12.5.1:
    q-values, ``*/*`` and ``type/*`` ranges); None when it allows any (no header, or ``*/*``
    alone); an empty tuple when it allows none of ours (406)."""
    if not accept or not accept.strip():
        return None
    ranked: list[tuple[float, int, str]] = []
    for i, item in enumerate(accept.split(",")):
        media, *params = [p.strip() for p in item.split(";")]
        q = 1.0
        for p in params:
            if p.lower().startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        media = media.lower()
        for full, fmt in MEDIA_FORMATS.items():
            if q > 0 and (media in (full, "*/*") or media == full.split("/")[0] + "/*"):
                ranked.append((-q, i, fmt))
    if not ranked:
        return ()
    order = tuple(dict.fromkeys(fmt for _, _, fmt in sorted(ranked)))
    return None if [m.strip().split(";")[0] for m in accept.split(",")] == ["*/*"] else order


def _plain_errors(exc: ValidationError) -> list[dict]:
    """Picklable error dicts: the location (prefixed with ``body``), message, type and the JSON
    parser's message (the only context the problem documents use)."""
    out = []
    for e in exc.errors(include_url=False):
        ctx = e.get("ctx") or {}
        out.append({"loc": ("body", *e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", "")),
                    "ctx": {"error": str(ctx["error"])} if "error" in ctx else {}})
    return out


def validate(body: bytes, context: KeyContext | None) -> tuple[DrapeRequest, str] | list[dict] | dict:
    """The validated request and its cache key, or without ``context`` its canonical JSON (what
    a job store keeps); or the errors; or ``{"not_acceptable": format}`` when the body names a
    format that ``context.accept`` refuses. Without a ``format`` in the body, the most preferred
    accepted one is used."""
    try:
        request = DrapeRequest.model_validate_json(body)
    except ValidationError as exc:
        return _plain_errors(exc)
    if context is not None and context.accept is not None:  # content negotiation: Accept picks the format
        if "format" in request.model_fields_set:
            if request.format not in context.accept:
                return {"not_acceptable": request.format}
        elif request.format != context.accept[0]:
            request = request.model_copy(update={"format": context.accept[0]})
    if context is None:
        return request, request.model_dump_json()
    return request, request_key(request, context.api_version, context.defaults, context.assets)


class RequestParser:
    """Validates drape request bodies: inline when small, in ``processes`` processes when large."""

    def __init__(self, processes: int = 1, inline_bytes: int = INLINE_BYTES):
        self.processes, self.inline_bytes = processes, inline_bytes
        self._executor: ProcessPoolExecutor | None = None

    def start(self) -> None:
        from service.pool import _context

        self._executor = ProcessPoolExecutor(max_workers=self.processes, mp_context=_context())

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None

    async def parse(self, request: Request, context: KeyContext | None = None) -> tuple[DrapeRequest, str]:
        """(request, its cache key) with ``context``; (request, its canonical JSON) without."""
        body = await request.body()
        if len(body) <= self.inline_bytes or self._executor is None:
            outcome = validate(body, context)
        else:
            outcome = await asyncio.get_running_loop().run_in_executor(self._executor, validate, body, context)
        if isinstance(outcome, list):
            raise RequestValidationError(outcome)
        if isinstance(outcome, dict):
            raise not_acceptable(f"the request asks for format {outcome['not_acceptable']!r}, which its Accept header refuses")
        return outcome


def not_acceptable(detail: str) -> ProblemException:
    return ProblemException(406, "Not acceptable", f"{detail}; this route answers {', '.join(MEDIA_FORMATS)}")


def request_body_openapi(example: dict) -> dict:
    """The OpenAPI request body of a route that reads a ``DrapeRequest`` itself."""
    return {"requestBody": {"required": True, "content": {"application/json": {
        "schema": {"$ref": "#/components/schemas/DrapeRequest"},
        "examples": {"walk_tshirt": {"summary": "neutral body, walk clip, T-shirt", "value": example}},
    }}}}
