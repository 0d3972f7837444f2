"""The /viewer routes without a browser (tests/test_viewer_browser.py drives the page): the page
and exactly the three.js files its imports reach, 503 problem+json without the npm package, open
under API-key auth, out of the API contract, and compressed, revalidated files."""
from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.config import Settings
from service.routes.viewer import PAGE_DIR, THREE_FILES

THREE = Settings().viewer_three_dir
needs_three = pytest.mark.skipif(not (THREE / "build" / "three.module.js").is_file(),
                                 reason="three.js not installed: run `npm ci` (or `npm ci --omit=dev`) at the repository root")
IMPORT = re.compile(r"""(?:^|\n)\s*(?:import|export)\b[^'"]*?\bfrom\s*['"]([^'"]+)['"]|import\s*['"]([^'"]+)['"]""")


def _imports(text: str) -> set[str]:
    return {a or b for a, b in IMPORT.findall(text)}


def _import_map() -> dict[str, str]:
    import json

    html = (PAGE_DIR / "index.html").read_text()
    return json.loads(re.search(r'<script type="importmap">(.*?)</script>', html, re.S).group(1))["imports"]


def _resolve(spec: str, importer: str, import_map: dict[str, str]) -> str:
    """A module specifier as the browser resolves it, as a path under /viewer/ (the import map for
    bare names, else relative to the importer)."""
    import posixpath

    if spec in import_map:
        return posixpath.normpath(import_map[spec].removeprefix("./"))
    for prefix, target in import_map.items():
        if prefix.endswith("/") and spec.startswith(prefix):
            return posixpath.normpath(target.removeprefix("./") + spec[len(prefix):])
    assert spec.startswith("."), f"{importer} imports {spec!r}: not in the import map"
    return posixpath.normpath(posixpath.join(posixpath.dirname(importer), spec))


@needs_three
def test_the_served_three_files_are_exactly_what_the_page_imports():
    """Follow every import from the page's own modules through three.js; each file reached is in
    THREE_FILES, and each of THREE_FILES is reached (nothing served that nothing loads)."""
    import_map = _import_map()
    pending, seen = ["viewer.js"], set()
    while pending:
        path = pending.pop()
        if path in seen:
            continue
        seen.add(path)
        file = PAGE_DIR / path if not path.startswith("vendor/three/") else THREE / path.removeprefix("vendor/three/")
        assert file.is_file(), path
        pending += [_resolve(spec, path, import_map) for spec in _imports(file.read_text())]
    reached = {p.removeprefix("vendor/three/") for p in seen if p.startswith("vendor/three/")}
    assert reached == set(THREE_FILES)
    assert {p for p in seen if not p.startswith("vendor/")} == {"viewer.js", "api.js"}


@needs_three
def test_page_and_vendor_files(client):
    r = client.get("/viewer", follow_redirects=False)
    assert r.status_code == 308 and r.headers["location"] == "/viewer/"
    page = client.get("/viewer/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html") and "importmap" in page.text
    assert "http://" not in page.text and "https://" not in page.text  # no CDN
    for name, kind in (("viewer.js", "javascript"), ("api.js", "javascript"), ("viewer.css", "text/css")):
        r = client.get(f"/viewer/{name}")
        assert r.status_code == 200 and kind in r.headers["content-type"], name
    for path in THREE_FILES:
        r = client.get(f"/viewer/vendor/three/{path}")
        assert r.status_code == 200 and "javascript" in r.headers["content-type"], path
    for path in ("package.json", "src/Three.js", "build/three.webgpu.js", "../../package.json", "build/../package.json"):
        r = client.get(f"/viewer/vendor/three/{path}")
        assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json"), path
    assert client.get("/viewer/nope.js").status_code == 404
    assert client.get("/viewer/../service/app.py").status_code == 404
    config = client.get("/viewer/config.json").json()
    assert config == {"auth": False, "api_key_header": "X-API-Key", "max_frames": 300, "job_max_frames": 3000, "max_garments": 4}


@needs_three
def test_files_are_gzipped_and_revalidated_per_coding(client):
    url = "/viewer/vendor/three/build/three.core.js"
    raw = (THREE / "build" / "three.core.js").read_bytes()
    plain = client.get(url, headers={"accept-encoding": "identity"})
    assert "content-encoding" not in plain.headers and plain.content == raw and plain.headers["cache-control"] == "no-cache"
    zipped = client.get(url, headers={"accept-encoding": "gzip"})
    assert zipped.headers["content-encoding"] == "gzip" and zipped.content == raw  # httpx decodes
    assert zipped.headers["etag"] == plain.headers["etag"][:-1] + '-gzip"'  # a strong tag per coding (RFC 9110 §8.8.3)
    for headers in ({"accept-encoding": "identity", "if-none-match": plain.headers["etag"]},
                    {"accept-encoding": "gzip", "if-none-match": zipped.headers["etag"]}):
        again = client.get(url, headers=headers)
        assert again.status_code == 304 and again.content == b"", headers
        assert again.headers["etag"] == headers["if-none-match"]
    # the identity copy's tag does not validate a gzip answer's bytes, nor the reverse, on If-Range
    ranged = client.get(url, headers={"accept-encoding": "gzip", "range": "bytes=0-9", "if-range": zipped.headers["etag"]})
    assert ranged.status_code == 200 and ranged.content == raw


def test_without_three_the_viewer_is_503_and_the_api_runs(runtime, tmp_path):
    settings = Settings().model_copy(update={"worker_mode": "thread", "workers": 1, "jobs_backend": "off", "viewer_three_dir": tmp_path / "three"})
    with TestClient(create_app(settings, runtime), raise_server_exceptions=False) as c:
        for path in ("/viewer", "/viewer/", "/viewer/viewer.js", "/viewer/vendor/three/build/three.module.js"):
            r = c.get(path, follow_redirects=False)
            assert r.status_code == 503 and r.headers["content-type"].startswith("application/problem+json"), path
            assert r.json()["detail"] == "viewer assets not installed: run npm ci --omit=dev", path
        assert c.get("/v1/garments").status_code == 200 and c.get("/readyz").status_code == 200


@needs_three
def test_the_viewer_is_open_under_api_key_auth(runtime):
    settings = Settings().model_copy(update={"worker_mode": "thread", "workers": 1, "jobs_backend": "off", "api_keys": "k1"})
    with TestClient(create_app(settings, runtime), raise_server_exceptions=False) as c:
        for path in ("/viewer", "/viewer/", "/viewer/viewer.js", "/viewer/vendor/three/build/three.module.js"):
            assert c.get(path, follow_redirects=False).status_code in (200, 308), path
        assert c.get("/viewer/config.json").json()["auth"] is True
        assert c.get("/v1/garments").status_code == 401  # the API is not
        assert c.get("/v1/garments", headers={"X-API-Key": "k1"}).status_code == 200


def test_the_viewer_is_not_in_the_contract(client):
    assert not [p for p in client.get("/openapi.json").json()["paths"] if p.startswith("/viewer")]
