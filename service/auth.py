"""Optional API-key auth: a header (X-API-Key by default) checked against keys from the
environment (TRYON_API_KEYS) or a file (TRYON_API_KEYS_FILE). 401 when the header is missing,
403 when the key is wrong, both problem+json. The comparison is constant time (hmac.compare_digest
against every configured key, so the time does not tell which key was close)."""
from __future__ import annotations

import hashlib
import hmac

from service.errors import problem_response

# Paths open without a key: probes, metrics (scraped inside the cluster), the contract and docs,
# and the try-on page with its files (service/routes/viewer.py; its calls to /v1 send the key).
PUBLIC_PATHS = frozenset({"/healthz", "/readyz", "/metrics", "/openapi.json", "/docs", "/viewer"})
PUBLIC_PREFIXES = ("/docs/assets/", "/viewer/")  # Swagger UI's own files (service/app.py), the page's


def key_matches(candidate: str, keys: list[bytes]) -> bool:
    """Constant-time: every key is compared (digests of equal length), whatever matches first."""
    digest = hashlib.sha256(candidate.encode("utf-8", "surrogateescape")).digest()
    found = False
    for key in keys:
        found |= hmac.compare_digest(digest, key)
    return found


def client_id(headers, header: str) -> str:
    """Who a job belongs to, for per-key quotas: a digest of the API key (never the key itself),
    or ``anonymous`` without one (call it only where the keys are checked: an unchecked header
    would let a client pick a fresh quota)."""
    key = headers.get(header)
    return "key:" + hashlib.sha256(key.encode("utf-8", "surrogateescape")).hexdigest()[:16] if key else "anonymous"


class ApiKeyAuth:
    """Pure ASGI middleware (runs before the body is read)."""

    def __init__(self, app, keys: list[str], header: str):
        self.app = app
        self.keys = [hashlib.sha256(k.encode()).digest() for k in keys]
        self.header = header.lower().encode()
        self.header_name = header

    async def __call__(self, scope, receive, send):
        path = scope.get("path", "")
        if scope["type"] != "http" or path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES) or scope["method"] == "OPTIONS":
            return await self.app(scope, receive, send)
        value = dict(scope.get("headers") or []).get(self.header)
        if value is None:
            status, title, detail = 401, "Unauthorized", f"the {self.header_name} header is required"
        elif not key_matches(value.decode("latin-1"), self.keys):
            status, title, detail = 403, "Forbidden", f"the {self.header_name} is not valid"
        else:
            return await self.app(scope, receive, send)
        headers = {"WWW-Authenticate": f'ApiKey header="{self.header_name}"'} if status == 401 else None
        response = problem_response(status, title, detail, scope["path"], headers=headers)
        await response(scope, receive, send)
