"""HTTP semantics the framework leaves out (pure ASGI middleware).

- ``HeadAsGet``: HEAD on any GET route answers the GET's status and headers without the body
  (RFC 9110 §9.3.2; FastAPI routes declare GET only, so HEAD would be 405).
- ``JsonOnly``: a POST with a body to a JSON route must say ``Content-Type: application/json``
  (or ``+json``); anything else is 415 with ``Accept-Post`` (RFC 9110 §15.5.16), before the
  body is parsed.
- ``CatalogCaching``: ETag, Cache-Control and 304 on the read-only catalog routes.
- ``EncodingTags``: a strong ETag of its own for a gzip-encoded answer (Starlette's
  ``GZipMiddleware`` compresses but keeps the identity answer's tag).
"""
from __future__ import annotations

import hashlib
import json

from isal import isal_zlib

from service.errors import PROBLEM_JSON


class HeadAsGet:
    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] != "HEAD":
            return await self.app(scope, receive, send)

        async def headers_only(message):
            if message["type"] == "http.response.body":
                if message.get("more_body", False):
                    return  # the rest of the body follows: send nothing until the last message
                message = {"type": "http.response.body", "body": b""}
            await send(message)

        await self.app({**scope, "method": "GET"}, receive, headers_only)


def is_json(content_type: str) -> bool:
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


class JsonOnly:
    def __init__(self, app, paths: frozenset[str]):
        self.app, self.paths = app, paths

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http" and scope["method"] == "POST" and scope.get("path") in self.paths:
            content_type = dict(scope.get("headers") or []).get(b"content-type", b"").decode("latin-1")
            if not is_json(content_type):
                body = json.dumps({"type": "about:blank", "title": "Unsupported media type", "status": 415,
                                   "detail": f"the body must be application/json, not {content_type[:100] or 'unlabelled'!r}",
                                   "instance": scope.get("path", "")}).encode()
                await send({"type": "http.response.start", "status": 415,
                            "headers": [(b"content-type", PROBLEM_JSON.encode()), (b"content-length", str(len(body)).encode()),
                                        (b"accept-post", b"application/json")]})
                await send({"type": "http.response.body", "body": body})
                return
        await self.app(scope, receive, send)


class CatalogCaching:
    """ETag and Cache-Control on the read-only catalog routes (garments, their templates,
    motions, the body model): their answers change only with the shipped assets, the garments'
    default methods or the API version, so the tag is a digest of those and the path; a GET or
    HEAD whose If-None-Match names it gets 304 without the route running (RFC 9110 §13.1.2)."""

    PREFIXES = ("/v1/garments", "/v1/motions", "/v1/body-model")
    CACHE_CONTROL = b"public, max-age=300"

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        path = scope.get("path", "")
        if scope["type"] != "http" or scope["method"] not in ("GET", "HEAD") or not path.startswith(self.PREFIXES):
            return await self.app(scope, receive, send)
        runtime = getattr(scope["app"].state, "runtime", None) if "app" in scope else None
        if runtime is None:
            return await self.app(scope, receive, send)
        tag = catalog_etag(scope["app"].version, runtime, path)
        given = dict(scope.get("headers") or []).get(b"if-none-match", b"").decode("latin-1")
        if tag in [t.strip().removeprefix("W/") for t in given.split(",")]:  # If-None-Match compares weakly (RFC 9110 §13.1.2)
            await send({"type": "http.response.start", "status": 304,
                        "headers": [(b"etag", tag.encode()), (b"cache-control", self.CACHE_CONTROL)]})
            await send({"type": "http.response.body", "body": b""})
            return

        async def tagged(message):
            if message["type"] == "http.response.start" and message["status"] == 200:
                kept = [(k, v) for k, v in message.get("headers", []) if k.lower() not in (b"etag", b"cache-control")]  # FileResponse's own
                message["headers"] = [*kept, (b"etag", tag.encode()), (b"cache-control", self.CACHE_CONTROL)]
            await send(message)

        await self.app(scope, receive, tagged)


def catalog_etag(api_version: str, runtime, path: str) -> str:
    """A strong tag: the catalog's bytes are the same for the same inputs."""
    defaults = json.dumps(runtime.defaults.as_dict(), sort_keys=True)
    digest = hashlib.sha256("\n".join([api_version, runtime.assets.combined, defaults, path]).encode()).hexdigest()
    return f'"{digest[:32]}"'


GZIP_SUFFIX = "-gzip"


GZIP_MIN_BYTES = 1024  # smaller answers are sent as they are
GZIP_LEVEL = 1  # GZipMiddleware's zlib level for the other answers (JSON, the viewer's files)
MESH_GZIP_LEVEL = 1  # ISA-L's level 1 (``isal_zlib``) for drape answers: ``gzip_mesh``


def gzip_mesh(payload: bytes) -> bytes:
    """The gzip coding (RFC 1952, any client decodes it) of a drape's glb or NPZ, deflated by
    ISA-L (``isal``, Intel's deflate with vectorised matching and Huffman coding) at its level 1.
    Measured on one core (T-shirt, ``dance``; session 33), zlib's Huffman-only strategy (the
    choice before: 2-3x less CPU than zlib level 1) against ISA-L level 1: 1-frame npz (faces
    included) 0.35 -> 0.234 MB in 2.1 ms against 0.241 MB in 0.64 ms; 30-frame npz 2.15 -> 1.886
    MB in 17.7 ms against 1.890 MB in 2.2 ms; 30-frame glb 2.06 -> 1.279 MB in 17.2 ms against
    1.293 MB in 4.5 ms; the README's 5.34 MB glb -> 3.43 MB in 44.7 ms against 3.32 MB in 9.9 ms.
    Deterministic (the gzip header has no time stamp): the answer's ETag names its bytes."""
    deflate = isal_zlib.compressobj(MESH_GZIP_LEVEL, isal_zlib.DEFLATED, 16 + isal_zlib.MAX_WBITS)
    return deflate.compress(payload) + deflate.flush()


def accepts_gzip(accept_encoding: str | None) -> bool:
    """Whether an ``Accept-Encoding`` value lets an answer be gzipped (GZipMiddleware's own test)."""
    return "gzip" in (accept_encoding or "")


class EncodingTags:
    """Entity tags per content coding, just outside ``GZipMiddleware``.

    A strong ETag names one sequence of bytes (RFC 9110 §8.8.1), and the gzip coding of an answer
    is other bytes: §8.8.3.3's example gives it a tag of its own. So a strong tag on an answer that
    left gzip-encoded becomes ``"<tag>-gzip"``; weak tags (the drape's ``W/"..."``: equivalent
    content, whatever the coding) pass unchanged. Inbound, ``If-None-Match`` reaches the routes
    (``CatalogCaching``, ``StaticFiles``) with the suffix removed, so they compare their own tags,
    and a 304 names the tag the client holds: the suffixed one when it sent that and accepts gzip.
    ``If-Range`` is left alone: a range of the gzip bytes is never a range of the identity bytes,
    so ``"<tag>-gzip"`` must not match there (the full answer is sent instead).
    """

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = scope.get("headers") or []
        given = dict(headers).get(b"if-none-match", b"").decode("latin-1")
        # the same test as GZipMiddleware's, so that "accepts gzip" means "would be answered in gzip"
        gzip_ok = accepts_gzip(dict(headers).get(b"accept-encoding", b"").decode("latin-1"))
        suffixed = {t.strip().removeprefix("W/")[: -len(GZIP_SUFFIX) - 1] + '"' for t in given.split(",") if t.strip().endswith(GZIP_SUFFIX + '"')}
        if suffixed:
            plain = ", ".join(t.strip().replace(GZIP_SUFFIX + '"', '"') for t in given.split(","))
            scope = {**scope, "headers": [(k, v) for k, v in headers if k != b"if-none-match"] + [(b"if-none-match", plain.encode("latin-1"))]}

        async def tag_per_coding(message):
            if message["type"] == "http.response.start":
                raw = message.get("headers", [])
                out = {k.lower(): v.decode("latin-1") for k, v in raw}
                tag = out.get(b"etag")
                if tag and not tag.startswith("W/") and tag.endswith('"'):
                    encoded = out.get(b"content-encoding") == "gzip"
                    held = message["status"] == 304 and gzip_ok and tag.removeprefix("W/") in suffixed
                    if encoded or held:
                        tagged = tag[:-1] + GZIP_SUFFIX + '"'
                        message["headers"] = [(k, tagged.encode("latin-1") if k.lower() == b"etag" else v) for k, v in raw]
            await send(message)

        await self.app(scope, receive, tag_per_coding)
