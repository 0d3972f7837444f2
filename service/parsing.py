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
from service.schemas import DrapeRequest

INLINE_BYTES = 256 * 1024


@dataclass(frozen=True)
class KeyContext:
    """What a request's cache key depends on besides the request (service.cache.request_key)."""

    api_version: str
    defaults: DefaultMethods
    assets: str


def _plain_errors(exc: ValidationError) -> list[dict]:
    """Picklable error dicts: the location (prefixed with ``body``), message, type and the JSON
    parser's message (the only context the problem documents use)."""
    out = []
    for e in exc.errors(include_url=False):
        ctx = e.get("ctx") or {}
        out.append({"loc": ("body", *e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", "")),
                    "ctx": {"error": str(ctx["error"])} if "error" in ctx else {}})
    return out


def validate(body: bytes, context: KeyContext | None) -> tuple[DrapeRequest, str] | list[dict]:
    """The validated request and its cache key, or without ``context`` its canonical JSON (what
    a job store keeps); or the errors."""
    try:
        request = DrapeRequest.model_validate_json(body)
    except ValidationError as exc:
        return _plain_errors(exc)
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
        return outcome


def request_body_openapi(example: dict) -> dict:
    """The OpenAPI request body of a route that reads a ``DrapeRequest`` itself."""
    return {"requestBody": {"required": True, "content": {"application/json": {
        "schema": {"$ref": "#/components/schemas/DrapeRequest"},
        "examples": {"walk_tshirt": {"summary": "neutral body, walk clip, T-shirt", "value": example}},
    }}}}
