"""FastAPI application factory; the lifespan loads the runtime once, starts the worker pool and
the job backend, and drains them on shutdown."""
from __future__ import annotations

import asyncio
import logging
import time
import uuid
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.middleware.gzip import GZipMiddleware
from fastapi.openapi.utils import get_openapi

from service.auth import ApiKeyAuth
from service.cache import ResultCache
from service.config import Settings
from service.errors import install_problem_handlers
from service.http_rules import GZIP_LEVEL, GZIP_MIN_BYTES, CatalogCaching, EncodingTags, HeadAsGet, JsonOnly
from service.limits import install_body_size_limit
from service.logs import REQUEST_ID_PATTERN, request_id_var
from service.metrics import Metrics
from service.parsing import RequestParser
from service.pool import WorkerPool
from service.routes import bodies, body_model, drape, garments, health, jobs, metrics, motions, viewer
from service.runtime import Runtime
from service.schemas import DrapeRequest, Problem

log = logging.getLogger(__name__)
access_log = logging.getLogger("service.access")

API_VERSION = "0.4.0"  # 0.4: the request's garment order is the layer order; 0.3: options.collisions (the 0.2 guard flags
# still read), motion.in_place, asf_amc motions


def description(s: Settings) -> str:
    return f"""\
3D virtual try-on: animated, skinned, collision-free garments on a parametric body (anny, rig cmu_mb).

Errors are RFC 9457 `application/problem+json` (no stack traces). Every response carries
`X-Request-ID` (the client's, when it sends a valid one). Units: metres, seconds, radians; body
model axes Z-up (glb output is Y-up).

Limits per request (defaults; deployments may change them, see the service settings):

| limit | POST /v1/drape | POST /v1/jobs |
|---|---|---|
| request body | {s.max_request_bytes} bytes | {s.job_max_request_bytes} bytes |
| BVH text, or ASF + AMC texts | {s.max_bvh_bytes} bytes | {s.max_bvh_bytes} bytes |
| source frames (poses, BVH, AMC) | {s.max_source_frames} | {s.max_source_frames} |
| output frames (after resampling) | {s.max_frames} | {s.job_max_frames} |
| garments | {s.max_garments} | {s.max_garments} |
| total vertices (frames x (garment vertices + body vertices if included)) | {s.max_total_vertices} | {s.job_max_total_vertices} |
| time | {s.request_timeout_s:g} s (504 after) | {s.job_timeout_s:g} s |

Load: synchronous drapes wait in a bounded queue ({s.max_queue} requests); when it is full, or the
expected wait exceeds {s.max_queue_wait_s:g} s, the answer is 503 with `Retry-After`. Job results are kept
{s.job_result_ttl_s:g} s.

Auth (when the deployment configures API keys): send the key in the `{s.api_key_header}` header;
a missing key is 401, a wrong one 403. `/healthz`, `/readyz` and `/metrics` are open.
"""


def create_app(settings: Settings | None = None, runtime: Runtime | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        state = app.state
        sweeper = None
        if state.runtime is None:
            # the API process drapes only with thread workers; process workers load the models themselves
            state.runtime = await asyncio.to_thread(Runtime.load, settings, settings.worker_mode == "thread")
        state.pool = WorkerPool(settings, state.runtime, state.metrics)
        await state.pool.start()
        if settings.worker_mode == "process":
            state.parser.start()  # large bodies are validated in a process of their own
        if settings.jobs_backend == "sqlite":
            from service.jobs import JobRunner, SqliteJobStore

            state.job_store = SqliteJobStore(settings)
            state.job_runner = JobRunner(state.job_store, state.pool, state.metrics)
            await state.job_runner.start()
        elif settings.jobs_backend == "redis":
            from service.jobs_redis import RedisJobStore

            state.job_store = RedisJobStore(settings)
            sweeper = asyncio.create_task(_sweep(state.job_store), name="tryon-redis-sweep")
        log.info("ready: %d garments, %d motions, jobs=%s", len(state.runtime.catalog.ids()), len(state.runtime.clips.ids()), settings.jobs_backend)
        try:
            yield
        finally:
            if sweeper is not None:
                sweeper.cancel()
            if state.job_runner is not None:
                await state.job_runner.stop()
            await state.pool.close()
            state.parser.close()
            if state.job_store is not None:
                state.job_store.close()
            log.info("stopped")

    app = FastAPI(title="Try-on service", version=API_VERSION, description=description(settings), lifespan=lifespan,
                  docs_url=None, redoc_url=None)
    install_docs(app)
    app.state.settings = settings
    app.state.runtime = runtime
    app.state.metrics = Metrics()
    app.state.cache = ResultCache(settings.cache_max_bytes)
    app.state.pool = None
    app.state.parser = RequestParser()
    app.state.job_store = None
    app.state.job_runner = None
    install_problem_handlers(app)
    # Middleware, innermost first: body size -> JSON only -> catalog caching -> auth -> CORS -> gzip -> its ETags -> HEAD as GET
    # -> request context (outermost).
    install_body_size_limit(app, settings.max_request_bytes, {"/v1/jobs": settings.job_max_request_bytes})
    app.add_middleware(JsonOnly, paths=frozenset({"/v1/drape", "/v1/jobs", "/v1/bodies/fit"}))
    app.add_middleware(CatalogCaching)  # inside the auth: a 304 is an answer too
    keys = settings.api_key_set()
    app.state.auth_on = bool(keys)  # job quotas are per key only where keys are checked
    if keys:
        app.add_middleware(ApiKeyAuth, keys=keys, header=settings.api_key_header)
    origins = settings.cors_origin_list()
    if origins:
        app.add_middleware(CORSMiddleware, allow_origins=origins, allow_methods=["GET", "POST", "DELETE", "OPTIONS"],
                           allow_headers=["content-type", settings.api_key_header, "x-request-id", "if-none-match"],
                           expose_headers=["etag", "location", "retry-after", "x-request-id", "x-frames", "x-cache", "server-timing"], max_age=600)
    # gzip when the client accepts it, on answers of 1 KB or more. Level 1: the README's glb (5.34 MB)
    # becomes 3.34 MB in 92 ms; level 6 3.23 MB in 301 ms, level 9 3.22 MB in 634 ms (one core).
    # (drape glbs and npzs are gzipped by their route, on a thread: service/routes/drape.py)
    app.add_middleware(GZipMiddleware, minimum_size=GZIP_MIN_BYTES, compresslevel=GZIP_LEVEL)
    app.add_middleware(EncodingTags)  # a strong ETag per coding (RFC 9110 §8.8.3)
    app.add_middleware(HeadAsGet)
    app.add_middleware(RequestContext, metrics=app.state.metrics)
    for module in (garments, body_model, bodies, motions, drape, jobs, health, metrics, viewer):
        app.include_router(module.router, responses=COMMON_ERRORS)
    app.openapi = lambda: problem_openapi(app)
    return app


DOCS_ASSETS = "/docs/assets"


def install_docs(app: FastAPI) -> None:
    """Swagger UI at ``/docs`` from the files of the ``swagger-ui-bundle`` package, served here:
    FastAPI's default loads them from a public CDN, so the page is blank on an offline or
    locked-down host."""
    from fastapi.openapi.docs import get_swagger_ui_html
    from fastapi.staticfiles import StaticFiles
    from swagger_ui_bundle import swagger_ui_path

    app.mount(DOCS_ASSETS, StaticFiles(directory=str(swagger_ui_path)), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def docs():
        return get_swagger_ui_html(openapi_url="/openapi.json", title=f"{app.title} - API docs",
                                   swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js", swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
                                   swagger_favicon_url=f"{DOCS_ASSETS}/favicon-32x32.png")


async def _sweep(store) -> None:
    """Redis backend: re-queue jobs whose worker died (``RedisJobStore.sweep_abandoned``)."""
    while True:
        await asyncio.sleep(store.sweep_every)
        try:
            await asyncio.to_thread(store.sweep_abandoned)
        except Exception:  # noqa: BLE001 - Redis away: /readyz says so; try again next time
            log.warning("jobs: the abandoned-job sweep failed", exc_info=True)


class RequestContext:
    """Request id (X-Request-ID in and out), one structured access-log line, and the HTTP
    metrics (by route template, so the label set stays bounded)."""

    def __init__(self, app, metrics: Metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        given = dict(scope.get("headers") or []).get(b"x-request-id", b"").decode("latin-1")
        rid = given if REQUEST_ID_PATTERN.match(given) else uuid.uuid4().hex
        token = request_id_var.set(rid)
        status = 500
        t0 = time.perf_counter()

        async def send_with_id(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                message["headers"] = [*message.get("headers", []), (b"x-request-id", rid.encode())]
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            elapsed = time.perf_counter() - t0
            self.metrics.requests.labels(template, scope["method"], str(status)).inc()
            self.metrics.latency.labels(template, scope["method"]).observe(elapsed)
            access_log.info("%s %s %d %.1f ms", scope["method"], scope["path"], status, elapsed * 1e3,
                            extra={"route": template, "status": status, "method": scope["method"], "duration_ms": round(elapsed * 1e3, 1)})
            request_id_var.reset(token)


COMMON_ERRORS = {
    422: {"description": "invalid request: the problem names the field"},
    500: {"description": "internal error (no details are disclosed)"},
}


def _deployment_limits(schemas: dict, settings: Settings) -> None:
    """The request schema's array and string bounds set to this deployment's limits, so that the
    contract refuses what the server refuses (the pydantic bounds are the hard caps)."""
    schemas["DrapeRequest"]["properties"]["garments"]["maxItems"] = settings.max_garments
    poses = schemas["PoseMotion"]["properties"]
    poses["rotations"]["maxItems"] = poses["translation"]["maxItems"] = settings.max_source_frames


def problem_openapi(app: FastAPI) -> dict:
    """The app's OpenAPI document, with every 4xx/5xx answer documented as problem+json, and the
    optional API-key scheme (401/403) on the /v1 routes."""
    if app.openapi_schema is None:
        settings = app.state.settings
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        problem_ref = {"$ref": "#/components/schemas/Problem"}
        components = schema.setdefault("components", {})
        schemas = components.setdefault("schemas", {})
        schemas.update(Problem.model_json_schema(ref_template="#/components/schemas/{model}")["$defs"])
        # the drape and job routes read their DrapeRequest body themselves (service/parsing.py)
        request_schema = DrapeRequest.model_json_schema(ref_template="#/components/schemas/{model}")
        schemas.update(request_schema.pop("$defs"))
        schemas["DrapeRequest"] = request_schema
        schemas["Problem"] = {k: v for k, v in Problem.model_json_schema(ref_template="#/components/schemas/{model}").items() if k != "$defs"}
        for name in ("HTTPValidationError", "ValidationError"):
            schemas.pop(name, None)
        components["securitySchemes"] = {"ApiKey": {"type": "apiKey", "in": "header", "name": settings.api_key_header,
                                                    "description": "only when the deployment configures API keys"}}
        _deployment_limits(schemas, settings)
        for path, item in schema["paths"].items():
            for operation in item.values():
                responses = operation.get("responses", {})
                if path.startswith("/v1/"):
                    operation["security"] = [{}, {"ApiKey": []}]  # optional: no key, or the key
                    responses.setdefault("401", {"description": "API key missing (when keys are configured)"})
                    responses.setdefault("403", {"description": "API key not valid"})
                for status, response in responses.items():
                    if status[0] in "45":
                        response["content"] = {"application/problem+json": {"schema": problem_ref}}
        app.openapi_schema = schema
    return app.openapi_schema
