"""FastAPI application factory; the lifespan loads the body model, catalog and clips once."""
from __future__ import annotations

import logging
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.config import Settings
from service.errors import install_problem_handlers
from service.limits import install_body_size_limit
from service.routes import body_model, drape, garments, health, motions
from service.runtime import Runtime
from service.schemas import Problem

log = logging.getLogger(__name__)

API_VERSION = "0.1.0"
DESCRIPTION = """\
3D virtual try-on: animated, skinned, collision-free garments on a parametric body (anny, rig cmu_mb).

Errors are RFC 9457 `application/problem+json`. Limits per request (defaults; see the service
settings): body <= 8 MiB, BVH text <= 4 MiB, <= 20,000 source frames, <= 300 output frames,
<= 4 garments. Units: metres, seconds, radians; body model axes Z-up (glb output is Y-up).
"""


def create_app(settings: Settings | None = None, runtime: Runtime | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        if app.state.runtime is None:
            app.state.runtime = Runtime.load(settings)
        log.info("runtime ready: %d garments, %d motions", len(app.state.runtime.catalog.ids()), len(app.state.runtime.clips.ids()))
        yield

    app = FastAPI(title="Try-on service", version=API_VERSION, description=DESCRIPTION, lifespan=lifespan)
    app.state.settings = settings
    app.state.runtime = runtime
    install_problem_handlers(app)
    install_body_size_limit(app, settings.max_request_bytes)
    for module in (garments, body_model, motions, drape, health):
        app.include_router(module.router, responses=COMMON_ERRORS)
    app.openapi = lambda: problem_openapi(app)
    return app


COMMON_ERRORS = {
    422: {"description": "invalid request: the problem names the field"},
    500: {"description": "internal error (no details are disclosed)"},
}


def problem_openapi(app: FastAPI) -> dict:
    """The app's OpenAPI document, with every 4xx/5xx answer documented as problem+json."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        problem_ref = {"$ref": "#/components/schemas/Problem"}
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        components.update(Problem.model_json_schema(ref_template="#/components/schemas/{model}")["$defs"])
        components["Problem"] = {k: v for k, v in Problem.model_json_schema(ref_template="#/components/schemas/{model}").items() if k != "$defs"}
        for name in ("HTTPValidationError", "ValidationError"):
            components.pop(name, None)
        for item in schema["paths"].values():
            for operation in item.values():
                for status, response in operation.get("responses", {}).items():
                    if status[0] in "45":
                        response["content"] = {"application/problem+json": {"schema": problem_ref}}
        app.openapi_schema = schema
    return app.openapi_schema
