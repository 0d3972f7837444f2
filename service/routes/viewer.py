"""GET /viewer: the try-on page (service/static/viewer/) and the three.js files it imports, served
from the ``three`` npm package (``npm ci --omit=dev``; ``Settings.viewer_three_dir``). Not part of
the API contract (no schema); open without an API key (service/auth.py), its calls to /v1 send it.
Without the npm package every /viewer path answers 503 problem+json, and the API runs as usual."""
from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import RedirectResponse, Response
from fastapi.staticfiles import StaticFiles

from service.errors import ProblemException

router = APIRouter(include_in_schema=False, tags=["viewer"])

PAGE_DIR = Path(__file__).resolve().parents[1] / "static" / "viewer"

# What the page's import map and the modules it imports need of the three package, and nothing
# else of it (tests/test_viewer.py follows every import of these files and checks the list).
THREE_FILES = frozenset({
    "build/three.module.js",
    "build/three.core.js",  # imported by three.module.js
    "examples/jsm/loaders/GLTFLoader.js",
    "examples/jsm/utils/BufferGeometryUtils.js",  # imported by GLTFLoader.js
    "examples/jsm/utils/SkeletonUtils.js",  # imported by GLTFLoader.js
    "examples/jsm/controls/OrbitControls.js",
    "examples/jsm/libs/meshopt_decoder.module.js",  # EXT_meshopt_compression
})

NOT_INSTALLED = "viewer assets not installed: run npm ci --omit=dev"
# revalidate every time (a 304 by ETag is cheap): the files change with the service and the package
CACHE_CONTROL = "no-cache"


def _three_dir(request: Request) -> Path:
    three = request.app.state.settings.viewer_three_dir
    if not (three / "build" / "three.module.js").is_file():
        raise ProblemException(503, "Viewer unavailable", NOT_INSTALLED)
    return three


async def _static(directory: Path, path: str, request: Request) -> Response:
    """A file under ``directory`` by StaticFiles (ETag, Last-Modified, 304, HEAD; 404 problem+json)."""
    response = await StaticFiles(directory=directory, check_dir=False).get_response(path, request.scope)
    response.headers["Cache-Control"] = CACHE_CONTROL
    return response


@router.get("/viewer")
def viewer(request: Request):
    """The page lives at /viewer/ (its relative URLs resolve there)."""
    _three_dir(request)
    return RedirectResponse("/viewer/", status_code=308)


@router.get("/viewer/config.json")
def viewer_config(request: Request) -> dict:
    """What the page needs to know of this deployment: whether it must send an API key (and in
    which header), and the frame limits that decide between POST /v1/drape and POST /v1/jobs."""
    _three_dir(request)
    s = request.app.state.settings
    return {"auth": bool(request.app.state.auth_on), "api_key_header": s.api_key_header, "max_frames": s.max_frames,
            "job_max_frames": s.job_max_frames, "max_garments": s.max_garments}


@router.get("/viewer/vendor/three/{path:path}")
async def three_file(request: Request, path: str):
    three = _three_dir(request)
    if path not in THREE_FILES:
        raise ProblemException(404, "Not found", f"{path!r} is not one of the three.js files the viewer serves")
    return await _static(three, path, request)


@router.get("/viewer/{path:path}")
async def page_file(request: Request, path: str):
    _three_dir(request)
    return await _static(PAGE_DIR, path or "index.html", request)
