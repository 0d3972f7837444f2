"""Content-addressed result cache: identical requests (same body, motion, garments, options and
format) on the same model versions and garment default methods get the same output, from memory.

The key is the SHA-256 of the canonical JSON of the validated request plus MODEL_VERSIONS (the
code's algorithm versions), the content version of the asset files a drape reads (``assets``:
``inference.asset_digest.AssetDigest.combined``, so a retrained model changes every key), the
garments' default methods (what a request's null fit / dynamics runs: a changed defaults file
changes the result) and the API version; it doubles as the response's ETag. The ETag is weak
(``W/"..."``): a result computed inside a merged batch may differ from the solo one at a few
guard-pushed vertices (service/batching.py), i.e. equivalent, not byte-identical. Concurrent identical requests are
coalesced: one computes, the others await it (single flight).
"""
from __future__ import annotations

import asyncio
import hashlib
import json
import threading
from collections import OrderedDict
from typing import Awaitable, Callable

from inference.defaults import DefaultMethods
from service.runtime import MODEL_VERSIONS, DrapeOutput
from service.schemas import DrapeRequest


def request_key(request: DrapeRequest, api_version: str, defaults: DefaultMethods, assets: str) -> str:
    methods = {gid: [e["fit"], e["dynamics"]] for gid, e in defaults.as_dict().items()}  # not the reasons: they change no output
    canonical = json.dumps(
        {"request": request.model_dump(mode="json"), "models": MODEL_VERSIONS, "assets": assets, "defaults": methods, "api": api_version},
        sort_keys=True, separators=(",", ":"),
    )
    return hashlib.sha256(canonical.encode()).hexdigest()


def etag_of(key: str) -> str:
    return f'W/"{key}"'


def etag_matches(if_none_match: str | None, key: str) -> bool:
    """RFC 9110 weak comparison of If-None-Match against this key's ETag ('*' is not a match
    here: see ``wildcard``)."""
    if not if_none_match:
        return False
    tags = [t.strip() for t in if_none_match.split(",")]
    return any(t.removeprefix("W/") == f'"{key}"' for t in tags)


def wildcard(if_none_match: str | None) -> bool:
    """``If-None-Match: *``: "only if no representation exists". A drape always has one, so on
    POST the condition is false and the answer is 412 (RFC 9110 §13.1.2)."""
    return bool(if_none_match) and "*" in [t.strip() for t in if_none_match.split(",")]


class ResultCache:
    """An LRU of outputs bounded by total payload bytes (0: caching off, coalescing still on)."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._entries: OrderedDict[str, DrapeOutput] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._inflight: dict[str, asyncio.Future] = {}

    def get(self, key: str) -> DrapeOutput | None:
        with self._lock:
            out = self._entries.get(key)
            if out is not None:
                self._entries.move_to_end(key)
            return out

    def put(self, key: str, out: DrapeOutput) -> None:
        size = len(out.payload)
        if size > self.max_bytes:
            return
        with self._lock:
            if key in self._entries:
                return
            self._entries[key] = out
            self._bytes += size
            while self._bytes > self.max_bytes:
                _, old = self._entries.popitem(last=False)
                self._bytes -= len(old.payload)

    @property
    def size_bytes(self) -> int:
        return self._bytes

    async def get_or_compute(self, key: str, compute: Callable[[], Awaitable[DrapeOutput]]) -> tuple[DrapeOutput, str]:
        """(output, 'hit' | 'coalesced' | 'miss')."""
        out = self.get(key)
        if out is not None:
            return out, "hit"
        waiting = self._inflight.get(key)
        if waiting is not None:
            return await asyncio.shield(waiting), "coalesced"
        future = asyncio.get_running_loop().create_future()
        self._inflight[key] = future
        try:
            out = await compute()
        except BaseException as exc:
            future.set_exception(exc)
            future.exception()  # retrieved: no "never retrieved" warning when nobody waits
            raise
        finally:
            self._inflight.pop(key, None)
        future.set_result(out)
        self.put(key, out)
        return out, "miss"
