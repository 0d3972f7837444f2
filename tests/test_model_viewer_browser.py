"""Our glb files in Google's ``<model-viewer>`` (npm ``@google/model-viewer``, its self-contained
``dist/model-viewer.min.js``, which bundles its own three.js r183), in headless Chromium on
SwiftShader as in tests/test_viewer_browser.py, against the real service.

It drapes the README request twice, plain and with ``"options": {"compression": "meshopt"}``
(EXT_meshopt_compression), and shows each glb in a ``<model-viewer>`` page: the ``load`` event
fires and ``error`` does not, the console stays clean, the ``tryon`` animation is there and lasts
2 s, and two times (0.5 s and 1.5 s) are drawn differently, the figure covering a fair share of the
element, the skin-toned body and the red T-shirt both visible, the shirt on the upper body.

Nothing may leave 127.0.0.1: model-viewer loads its DRACO and KTX2 decoders from gstatic.com
(on demand, only for glbs that use them), and its meshopt decoder from wherever
``self.ModelViewerElement.meshoptDecoderLocation`` says: it has no default, and without it a
meshopt glb fails to load (a test below checks). model-viewer awaits a *classic* script there and
then decodes with the MeshoptDecoder in its bundle, so the page points it at meshoptimizer's
classic-script decoder (npm ``meshoptimizer``, ``meshopt_decoder.cjs``, a devDependency), served
locally. Every request of the browser context is logged and any that is not for 127.0.0.1 is
refused and fails the test.

Screenshots (the two times side by side, 256 colours) go to build/model_viewer/, and to
docs/viewer/ with TRYON_UPDATE_SCREENSHOTS=1."""
from __future__ import annotations

import io
import os
import time
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest

from tests.conftest import REPO_ROOT

MODEL_VIEWER = REPO_ROOT / "node_modules" / "@google" / "model-viewer" / "dist" / "model-viewer.min.js"
MESHOPT_DECODER = REPO_ROOT / "node_modules" / "meshoptimizer" / "meshopt_decoder.cjs"
UPDATE = os.environ.get("TRYON_UPDATE_SCREENSHOTS") == "1"
SHOTS = REPO_ROOT / "build" / "model_viewer"
DOC_SHOTS = REPO_ROOT / "docs" / "viewer"
README_REQUEST = {"body": {"phenotypes": {"gender": 0.5, "age": 0.8, "weight": 0.5, "height": 0.5}},
                  "motion": {"type": "clip", "clip": "walk", "duration_s": 2.0},
                  "garments": [{"id": "tshirt"}], "format": "glb"}
SIZE = {"width": 360, "height": 540}  # the <model-viewer> element, CSS px (device scale 1)
BACKGROUND = (255, 255, 255)

sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed: pip install -e '.[test]'")
Image = pytest.importorskip("PIL.Image", reason="Pillow not installed")
from tests.test_viewer_browser import CHROMIUM, CHROMIUM_ARGS, _serve, browser  # noqa: E402,F401  (after the skips it needs; browser: the shared fixture)

pytestmark = [
    pytest.mark.skipif(not CHROMIUM.is_file(), reason=f"{CHROMIUM} missing: apt-get install chromium (.ci/run does)"),
    pytest.mark.skipif(not MODEL_VIEWER.is_file(), reason="@google/model-viewer not installed: run `npm ci` at the repository root"),
    pytest.mark.skipif(not MESHOPT_DECODER.is_file(), reason="meshoptimizer (npm) not installed: run `npm ci` at the repository root"),
    pytest.mark.timeout(180),
]

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>model-viewer: {name}</title>
<style>html, body {{ margin: 0; background: #fff; }}
model-viewer {{ width: {width}px; height: {height}px; background-color: #fff; --poster-color: #fff; }}</style>
<script>{config}</script>
<script type="module" src="/__mv/model-viewer.min.js"></script>
</head><body>
<model-viewer id="mv" src="/__mv/{name}.glb" alt="try-on" animation-name="tryon" autoplay
  interaction-prompt="none" camera-orbit="20deg 80deg auto"><div slot="progress-bar"></div></model-viewer>
<script>
  window.mvEvents = [];
  const mv = document.querySelector('#mv');
  mv.addEventListener('load', () => window.mvEvents.push(['load', null]));
  mv.addEventListener('error', e => window.mvEvents.push(['error', JSON.stringify(e.detail, (k, v) => v instanceof Error ? String(v) : v)]));
</script>
</body></html>"""
LOCAL_DECODER = "self.ModelViewerElement = {meshoptDecoderLocation: '/__mv/meshopt_decoder.js'};"


@pytest.fixture(scope="module")
def glbs(tmp_path_factory):
    """The README drape, plain and meshopt-compressed, from ``python -m service``."""
    out = {}
    with _serve(tmp_path_factory.mktemp("jobs")) as url:
        for name, extra in (("plain", {}), ("meshopt", {"options": {"compression": "meshopt"}})):
            r = httpx.post(url + "/v1/drape", json={**README_REQUEST, **extra}, timeout=120)
            if name == "meshopt" and r.status_code == 422 and "compress" in r.text:
                pytest.skip(f"this service writes no meshopt glb (the 'compress' extra): {r.text[:200]}")
            assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary", (r.status_code, r.text[:300])
            assert r.content[:4] == b"glTF"
            out[name] = r.content
    assert b"EXT_meshopt_compression" in out["meshopt"][:200_000] and b"EXT_meshopt_compression" not in out["plain"][:200_000]
    return out


class Session:
    """A browser context whose requests are all logged and served here: the page, model-viewer,
    the decoder and the glbs under http://127.0.0.1:9/__mv/ (nothing listens there: every request
    is answered by the route); any other address is refused and recorded."""

    ORIGIN = "http://127.0.0.1:9"

    def __init__(self, browser, glbs: dict[str, bytes], config: str):
        self.files = {"model-viewer.min.js": (MODEL_VIEWER.read_bytes(), "text/javascript"),
                      "meshopt_decoder.js": (MESHOPT_DECODER.read_bytes(), "text/javascript")}
        for name, data in glbs.items():
            self.files[f"{name}.glb"] = (data, "model/gltf-binary")
            self.files[f"{name}.html"] = (PAGE.format(name=name, config=config, **SIZE).encode(), "text/html")
        self.requests: list[str] = []
        self.refused: list[str] = []
        self.errors: list[str] = []
        self.context = browser.new_context(viewport={"width": SIZE["width"] + 40, "height": SIZE["height"] + 40}, device_scale_factor=1)
        self.context.on("request", lambda r: self.requests.append(r.url))
        self.context.route("**/*", self._answer)

    def _answer(self, route):
        url = urlsplit(route.request.url)
        if url.scheme in ("http", "https") and f"{url.scheme}://{url.netloc}" == self.ORIGIN and url.path.startswith("/__mv/"):
            name = url.path.removeprefix("/__mv/")
            if name in self.files:
                body, kind = self.files[name]
                return route.fulfill(status=200, body=body, content_type=kind, headers={"access-control-allow-origin": "*"})
            return route.fulfill(status=404, body=b"not here")
        self.refused.append(route.request.url)
        return route.abort()

    def open(self, name: str):
        page = self.context.new_page()
        page.on("console", lambda m: self.errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))
        page.goto(f"{self.ORIGIN}/__mv/{name}.html")
        page.wait_for_function("window.mvEvents.length > 0", timeout=60_000)
        return page

    def outside(self) -> list[str]:
        """Requests that were not for 127.0.0.1 (data: and blob: URLs stay in the page)."""
        return [u for u in self.requests if urlsplit(u).scheme not in ("data", "blob") and urlsplit(u).hostname != "127.0.0.1"] + self.refused


@pytest.fixture
def session(browser, glbs):
    s = Session(browser, glbs, LOCAL_DECODER)
    yield s
    s.context.close()


def _shot(page, t: float) -> np.ndarray:
    """The element drawn at animation time ``t`` (paused): (H, W, 3) uint8."""
    page.evaluate("t => { const mv = document.querySelector('#mv'); mv.pause(); mv.currentTime = t; }", t)
    page.wait_for_function("t => Math.abs(document.querySelector('#mv').currentTime - t) < 1e-3", arg=t)
    for _ in range(2):  # model-viewer renders on its own animation frame once told it needs to
        page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(() => requestAnimationFrame(r))))")
    return np.asarray(Image.open(io.BytesIO(page.locator("#mv").screenshot())).convert("RGB"))


def _figure(img: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that are not the white background (by more than 24 of 255 in a channel)."""
    return np.abs(img.astype(np.int16) - np.array(BACKGROUND, np.int16)).max(axis=-1) > 24


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=-1) > 24


def _red(img: np.ndarray) -> np.ndarray:
    """Red-dominant pixels: the T-shirt (sRGB #a8323a, lit and tone mapped)."""
    r, g, b = (img[..., i].astype(np.int16) for i in range(3))
    return (r > 60) & (g < 0.55 * r) & (b < 0.6 * r)


def _skin(img: np.ndarray) -> np.ndarray:
    """Warm, light, moderately saturated pixels: the body (linear base colour 0.604, 0.402, 0.296)."""
    r, g, b = (img[..., i].astype(np.int16) for i in range(3))
    return (r > 90) & (g > 0.6 * r) & (g < 0.95 * r) & (b < 0.97 * g) & (r - b > 25)


def _save(name: str, images: list[np.ndarray]) -> None:
    """The times side by side, as a 256-colour PNG: build/model_viewer/ (and docs/viewer/ when asked)."""
    sheet = Image.fromarray(np.concatenate(images, axis=1)).quantize(256)
    for folder in (SHOTS, DOC_SHOTS) if UPDATE else (SHOTS,):
        folder.mkdir(parents=True, exist_ok=True)
        sheet.save(folder / f"model_viewer_{name}.png", optimize=True)


DRAWN: dict[str, np.ndarray] = {}  # each glb's image at 0.5 s, to compare the two


@pytest.mark.parametrize("name", ["plain", "meshopt"])
def test_model_viewer_plays_the_readme_glb(session, name):
    t0 = time.monotonic()
    page = session.open(name)
    events = page.evaluate("window.mvEvents")
    assert events == [["load", None]], events  # loaded, no error event
    state = page.evaluate("""() => { const mv = document.querySelector('#mv');
        return {loaded: mv.loaded, visible: mv.modelIsVisible, animations: mv.availableAnimations, duration: mv.duration}; }""")
    assert state["loaded"] and state["animations"] == ["tryon"], state
    assert state["duration"] == pytest.approx(2.0, abs=1e-3), state  # 61 frames at 30 fps
    page.wait_for_function("document.querySelector('#mv').modelIsVisible")

    early, late = _shot(page, 0.5), _shot(page, 1.5)
    again = _shot(page, 0.5)
    figure = _figure(early)
    assert 0.06 < figure.mean() < 0.7, f"the figure covers {figure.mean():.1%} of the element"
    ys, _ = np.nonzero(figure)
    top, bottom = ys.min(), ys.max()
    assert bottom - top > 0.5 * figure.shape[0], "model-viewer frames the body at least half the element high"
    moved = _changed(early, late)
    assert moved.sum() > 0.1 * figure.sum(), f"t=0.5 s vs 1.5 s: {moved.sum()} px changed of the figure's {figure.sum()}"
    assert _changed(early, again).sum() < 0.01 * figure.size, "the same time draws the same image"

    for img, t in ((early, 0.5), (late, 1.5)):
        red, skin = _red(img) & _figure(img), _skin(img) & _figure(img)
        fig = _figure(img).sum()
        assert red.sum() > 0.2 * fig, f"t={t}: red (T-shirt) on {red.sum()} px of the figure's {fig}"
        assert skin.sum() > 0.3 * fig, f"t={t}: skin (body) on {skin.sum()} px of the figure's {fig}"
        ry, _ = np.nonzero(red)
        sy, _ = np.nonzero(skin)
        assert np.median(ry) < top + 0.55 * (bottom - top), "the T-shirt is on the upper body"
        assert sy.min() < ry.min() and sy.max() > ry.max(), "skin above (the head) and below (the legs) the shirt"

    _save(name, [early, late])
    DRAWN[name] = early
    if name == "meshopt" and "plain" in DRAWN:  # the same geometry decoded (pixel-identical when written)
        assert _changed(DRAWN["plain"], early).sum() < 0.01 * figure.sum(), "the meshopt glb draws as the plain one"
    assert session.errors == [], session.errors
    assert session.outside() == [], f"requests that left 127.0.0.1: {session.outside()}"
    local = {urlsplit(u).path for u in session.requests}
    assert f"/__mv/{name}.glb" in local and "/__mv/model-viewer.min.js" in local
    # model-viewer fetches its meshopt decoder when told where it is, for every glb
    assert "/__mv/meshopt_decoder.js" in local
    assert time.monotonic() - t0 < 60


def test_without_a_decoder_location_model_viewer_refuses_the_meshopt_glb(browser, glbs):
    """Why the page sets ``meshoptDecoderLocation``: model-viewer has no default for it (and so
    fetches nothing), and the EXT_meshopt_compression glb then fails with an ``error`` event."""
    s = Session(browser, glbs, "")
    try:
        page = s.open("meshopt")
        events = page.evaluate("window.mvEvents")
        assert [e[0] for e in events] == ["error"], events
        assert '"type":"loadfailure"' in events[0][1], events
        assert any("setMeshoptDecoder must be called before loading compressed files" in e for e in s.errors), s.errors
        assert s.outside() == [], s.outside()
        assert "/__mv/meshopt_decoder.js" not in {urlsplit(u).path for u in s.requests}
    finally:
        s.context.close()
