"""Request-size limit, enforced before the body is parsed (pure ASGI middleware)."""
from __future__ import annotations

import json

from fastapi import FastAPI

from service.errors import PROBLEM_JSON


class BodySizeLimit:
    """Answers 413 problem+json when a request body exceeds ``max_bytes``, declared
    (Content-Length) or streamed (chunked transfer).

    A declared length is checked before anything is read, and the app then reads the body itself
    (so that it can refuse work before reading it). A streamed body, of unknown length, is read
    here up to the limit and handed to the app in one message: one that grows past the limit is
    refused before the app sees any of it (an error raised inside the app's receive would reach
    the app's own error handling instead)."""

    def __init__(self, app, max_bytes: int, path_limits: dict[str, int] | None = None):
        self.app = app
        self.default_bytes = max_bytes
        self.path_limits = path_limits or {}

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS", "DELETE"):
            return await self.app(scope, receive, send)
        max_bytes = self.path_limits.get(scope.get("path", ""), self.default_bytes)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None:  # the server delivers at most the declared length: the app reads it as it likes
            if not declared.isdigit() or int(declared) > max_bytes:
                return await self._reject(scope, send, max_bytes)
            return await self.app(scope, receive, send)
        chunks, received = [], 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away
                return
            chunk = message.get("body", b"")
            received += len(chunk)
            if received > max_bytes:
                return await self._reject(scope, send, max_bytes)
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        replayed = False

        async def replay():
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": b"".join(chunks), "more_body": False}
            return await receive()  # after the body: http.disconnect

        await self.app(scope, replay, send)

    async def _reject(self, scope, send, max_bytes: int):
        body = json.dumps(
            {"type": "about:blank", "title": "Request too large", "status": 413,
             "detail": f"request body exceeds {max_bytes} bytes", "instance": scope.get("path", "")}
        ).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", PROBLEM_JSON.encode()), (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})


def install_body_size_limit(app: FastAPI, max_bytes: int, path_limits: dict[str, int] | None = None) -> None:
    """``max_bytes`` for every path, except those named in ``path_limits`` (POST /v1/jobs)."""
    app.add_middleware(BodySizeLimit, max_bytes=max_bytes, path_limits=path_limits)
