"""Request-size limit, enforced before the body is parsed (pure ASGI middleware)."""
from __future__ import annotations

import json

from fastapi import FastAPI

from service.errors import PROBLEM_JSON


class BodySizeLimit:
    """Answers 413 problem+json when a request body exceeds ``max_bytes`` (declared or streamed)."""

    def __init__(self, app, max_bytes: int, path_limits: dict[str, int] | None = None):
        self.app = app
        self.default_bytes = max_bytes
        self.path_limits = path_limits or {}

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        max_bytes = self.path_limits.get(scope.get("path", ""), self.default_bytes)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > max_bytes):
            return await self._reject(scope, send, max_bytes)
        received = 0
        too_large = False

        async def limited_receive():
            nonlocal received, too_large
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > max_bytes:
                    too_large = True
                    raise _TooLarge()
            return message

        try:
            await self.app(scope, limited_receive, send)
        except _TooLarge:
            await self._reject(scope, send, max_bytes)

    async def _reject(self, scope, send, max_bytes: int):
        body = json.dumps(
            {"type": "about:blank", "title": "Request too large", "status": 413,
             "detail": f"request body exceeds {max_bytes} bytes", "instance": scope.get("path", "")}
        ).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", PROBLEM_JSON.encode()), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


class _TooLarge(Exception):
    pass


def install_body_size_limit(app: FastAPI, max_bytes: int, path_limits: dict[str, int] | None = None) -> None:
    """``max_bytes`` for every path, except those named in ``path_limits`` (POST /v1/jobs)."""
    app.add_middleware(BodySizeLimit, max_bytes=max_bytes, path_limits=path_limits)
