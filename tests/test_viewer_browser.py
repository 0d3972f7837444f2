"""The /viewer page in a real browser: headless Chromium (Debian's ``chromium`` package, driven by
Playwright; nothing is downloaded) against the real service (``python -m service`` on a free
port). WebGL runs on SwiftShader (the CPU), so no GPU is needed.

It drapes the README request (neutral body, walk, 2 s, T-shirt) and reads the canvas back: the
body and the garment are drawn (hiding each changes the pixels where it is), the animation moves
(two scrubbed times differ), the figures the service returned are shown, and the console has no
errors. Then the measurements form: an impossible body shows the 422's errors, a possible one is
fitted (the sliders take the fitted phenotypes) and draped through a job. Last, a deployment with
API keys: the page loads without one and sends the one typed in; and a drape refused as too long
is sent as a job. Screenshots go to build/viewer/ (docs/viewer/ with TRYON_UPDATE_SCREENSHOTS=1)."""
from __future__ import annotations

import contextlib
import io
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.conftest import REPO_ROOT

CHROMIUM = Path(os.environ.get("TRYON_TEST_CHROMIUM", "/usr/bin/chromium"))
# The screenshots: build/viewer/ on every run; docs/viewer/ (committed) with TRYON_UPDATE_SCREENSHOTS=1,
# so that a test run does not rewrite tracked files (each shows its round-trip time, different every run).
SHOTS = REPO_ROOT / ("docs" if os.environ.get("TRYON_UPDATE_SCREENSHOTS") == "1" else "build") / "viewer"
THREE = REPO_ROOT / "node_modules" / "three" / "build" / "three.module.js"
# WebGL without a GPU: ANGLE on SwiftShader (the flag keeps it allowed: Chromium 13x+ wants it said)
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--no-sandbox"]
VIEWPORT = {"width": 1280, "height": 760}

pytestmark = [
    pytest.mark.skipif(not CHROMIUM.is_file(), reason=f"{CHROMIUM} missing: apt-get install chromium (.ci/run does)"),
    pytest.mark.skipif(not THREE.is_file(), reason="three.js not installed: run `npm ci` at the repository root"),
    pytest.mark.timeout(180),
]
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed: pip install -e '.[test]'")
Image = pytest.importorskip("PIL.Image", reason="Pillow not installed")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def _serve(jobs_dir: Path, **env: str):
    """``python -m service`` on a free port, as deployed (process workers, the SQLite job store)."""
    port = _free_port()
    env = {**os.environ, "TRYON_JOBS_DIR": str(jobs_dir), "TRYON_WORKERS": "1", "TRYON_LOG_LEVEL": "warning", "TRYON_JOB_POLL_S": "0.1",
           "TRYON_JOB_CHUNK_FRAMES": "20", **env}
    proc = subprocess.Popen([sys.executable, "-m", "service", "--port", str(port), "--workers", "1", "--log-level", "warning"],
                            cwd=REPO_ROOT, env=env, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        t0 = time.monotonic()
        while True:
            assert proc.poll() is None, "the service exited"
            assert time.monotonic() - t0 < 90, "the service did not get ready"
            try:
                if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        yield url
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


@pytest.fixture(scope="module")
def service_url(tmp_path_factory):
    with _serve(tmp_path_factory.mktemp("jobs")) as url:
        yield url


class Console:
    """Every console error and uncaught exception of the page."""

    def __init__(self, page):
        self.errors: list[str] = []
        page.on("console", lambda m: self.errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


def _open(browser, url: str):
    page = browser.new_page(viewport=VIEWPORT)
    page.console = Console(page)
    page.goto(url + "/viewer")
    page.wait_for_function("document.querySelector('#status').dataset.state !== 'loading'", timeout=30_000)
    assert page.get_attribute("#status", "data-state") == "idle", page.inner_text("#problem")
    return page


@pytest.fixture
def page(browser, service_url):
    page = _open(browser, service_url)
    yield page
    page.close()


def _wait_ready(page, timeout_ms=60_000) -> None:
    page.wait_for_function("['ready', 'error'].includes(document.querySelector('#status').dataset.state)", timeout=timeout_ms)
    assert page.get_attribute("#status", "data-state") == "ready", page.inner_text("#problem")


def _canvas(page) -> np.ndarray:
    """The canvas as drawn now: (H, W, 3) uint8, after two more frames were rendered."""
    page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    return np.asarray(Image.open(io.BytesIO(page.locator("#scene").screenshot())).convert("RGB"))


def _scrub(page, t: float) -> None:
    page.eval_on_selector("#scrub", "(s, t) => { s.value = String(t); s.dispatchEvent(new Event('input')); }", t)
    page.wait_for_function("t => Math.abs(Number(document.querySelector('#scene').dataset.time) - t) < 1e-3", arg=t)


def _show(page, node: str, visible: bool) -> None:
    box = page.locator(f"#visibility input[data-node='{node}']")
    box.set_checked(visible)


def _save(page, name: str) -> None:
    """The page as a 256-colour PNG (a third of the true-colour file's size)."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    Image.open(io.BytesIO(page.screenshot())).convert("RGB").quantize(256).save(SHOTS / name, optimize=True)


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that differ by more than 24 (of 255) in a channel."""
    return np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=-1) > 24


def _rows(page, section: str) -> dict[str, str]:
    """The figures panel's table under the heading ``section``: first column -> second."""
    return page.evaluate("""title => {
        const h = [...document.querySelectorAll('#answer h3')].find(x => x.textContent === title);
        if (!h) return null;
        return Object.fromEntries([...h.parentElement.querySelectorAll('tr')].map(r => [r.cells[0].textContent, r.cells[1]?.textContent]));
    }""", section)


def test_drape_shows_the_body_and_the_garment_moving(page):
    t0 = time.monotonic()
    order = page.inner_text("#layer-order")
    assert order == "T-shirt", order  # the default choice
    # the README request: neutral body (the sliders' defaults), walk, 2 s, T-shirt
    assert page.input_value("#motion-clip") == "walk" and page.input_value("#duration-s") == "2"
    page.click("#drape")
    _wait_ready(page)
    answer = _rows(page, "Answer")
    assert answer["route"] == "POST /v1/drape" and answer["X-Frames"] == "61" and answer["Content-Encoding"] == "gzip", answer
    timing = _rows(page, "Server-Timing (ms)")
    # the T-shirt's default fit 'canonical' is collision-free by construction: no guard stage, the final repair only
    assert {"skin", "repair", "export", "total"} <= set(timing) and float(timing["total"]) > 0, timing
    extras = _rows(page, "asset.extras")
    assert extras["frames"] == "61" and extras["fps"] == "30" and extras["garments"] == "tshirt" and extras["in_place"] == "true"
    assert _rows(page, "Model versions")["body"].startswith("anny-")
    assert _rows(page, "Phenotypes")["weight"] == "0.500"

    page.click("#play")  # pause
    assert page.inner_text("#play") == "Play"
    _scrub(page, 0.5)
    dressed = _canvas(page)
    _show(page, "tshirt", False)
    undressed = _canvas(page)
    _show(page, "body", False)
    empty = _canvas(page)  # the floor and the background only
    _show(page, "tshirt", True)
    shirt_only = _canvas(page)
    _show(page, "body", True)

    figure = _changed(dressed, empty)  # where the body and the garment are drawn
    shirt = _changed(dressed, undressed)  # where the garment hides the body (or the background)
    shirt_alone = _changed(shirt_only, empty)
    area = figure.size
    assert figure.mean() > 0.06, f"body + garment on {figure.mean():.1%} of the canvas"
    assert shirt.sum() > 0.15 * figure.sum(), f"the garment changes {shirt.sum()} px of the figure's {figure.sum()}"
    assert shirt_alone.sum() > 0.15 * figure.sum() and shirt_alone.sum() < 0.8 * figure.sum()
    ys, xs = np.nonzero(figure)
    top, bottom, left, right = ys.min(), ys.max(), xs.min(), xs.max()
    assert bottom - top > 0.5 * figure.shape[0], "the body is framed at least half the canvas high"
    sy, sx = np.nonzero(shirt)
    # the garment is on the body: inside its box, in the upper half (a T-shirt)
    assert top <= sy.min() and sy.max() <= bottom and left <= sx.min() and sx.max() <= right
    assert np.median(sy) < top + 0.55 * (bottom - top)

    _scrub(page, 1.5)
    later = _canvas(page)
    moved = _changed(dressed, later)
    assert moved.sum() > 0.1 * figure.sum(), f"t=0.5 s vs 1.5 s: {moved.sum()} px changed of {figure.sum()}"
    assert page.inner_text("#time") == "1.50 s · frame 46/61"
    _scrub(page, 0.5)
    again = _canvas(page)
    assert _changed(dressed, again).sum() < 0.01 * area, "the same time draws the same image"

    page.eval_on_selector("#controls", "c => { c.scrollTop = 0; }")
    _save(page, "viewer_walk_tshirt.png")
    assert page.console.errors == [], page.console.errors
    assert time.monotonic() - t0 < 60


def test_measurements_fit_then_drape_through_a_job(page, service_url):
    page.check("input[name='body-mode'][value='measurements']")
    assert page.is_visible("#fit-form") and not page.is_visible("#phenotype-sliders")
    neutral = httpx.get(service_url + "/v1/bodies/measurements").json()["measurements"]
    assert float(page.input_value("input[name='height_cm']")) == pytest.approx(neutral["height_cm"], abs=0.05)  # prefilled

    # a chest far past what the other measurements allow: the 422's errors, the field marked
    page.fill("input[name='chest_cm']", "150")
    with page.expect_response("**/v1/bodies/fit") as refused:
        page.click("#fit")
    assert refused.value.status == 422
    page.wait_for_selector("#problem:not([hidden])")
    problem = page.inner_text("#problem")
    expected = refused.value.json()
    assert expected["title"] in problem and expected["detail"] in problem
    for e in expected["errors"]:
        assert e["detail"] in problem
    assert "invalid" in page.get_attribute("input[name='chest_cm']", "class")

    # a body the model has (a heavier, more male one), with its weight and gender
    target = httpx.get(service_url + "/v1/bodies/measurements", params={"weight": 0.7, "gender": 0.2}).json()["measurements"]
    for name in ("height_cm", "chest_cm", "waist_cm", "hips_cm", "inseam_cm", "weight_kg"):
        page.fill(f"input[name='{name}']", f"{target[name]:.1f}")
    page.select_option("select[name='gender']", "male")
    with page.expect_response("**/v1/bodies/fit") as fitted:
        page.click("#fit")
    assert fitted.value.status == 200
    page.wait_for_function("document.querySelector('#status').dataset.state === 'idle'")
    fit = fitted.value.json()
    assert page.is_hidden("#problem")
    shown = page.inner_text("#fit-result")
    assert "residual" in shown and f"{fit['phenotypes']['weight']:.3f}" in shown
    sliders = page.eval_on_selector_all("#phenotype-sliders input", "s => Object.fromEntries(s.map(x => [x.name, Number(x.value)]))")
    for name, value in fit["phenotypes"].items():
        assert sliders[name] == pytest.approx(value, abs=0.006), name  # the sliders' step is 0.01

    page.select_option("#route", "job")
    page.fill("#duration-s", "1")
    page.evaluate("""() => {  // every status line and progress value the page shows
        window.statusLog = [];
        new MutationObserver(() => window.statusLog.push([document.querySelector('#status-text').textContent,
                                                          document.querySelector('#progress').hidden ? null : document.querySelector('#progress').value]))
            .observe(document.querySelector('#status'), {subtree: true, childList: true, characterData: true, attributes: true});
    }""")
    with page.expect_response("**/v1/jobs") as accepted:
        page.click("#drape")
    assert accepted.value.status == 202
    _wait_ready(page)
    log = page.evaluate("window.statusLog")
    assert any(text.startswith("job ") and "%" in text and value is not None for text, value in log), log
    answer = _rows(page, "Answer")
    assert answer["route"].startswith("POST /v1/jobs") and answer["X-Frames"] == "31", answer
    phenotypes = _rows(page, "Phenotypes")
    assert float(phenotypes["weight"]) == pytest.approx(fit["phenotypes"]["weight"], abs=0.006)
    page.click("#play")
    _scrub(page, 0.5)
    _save(page, "viewer_fit.png")
    # the one console error: Chromium's own line for the 422 the test asked for
    assert [e for e in page.console.errors if "status of 422" not in e] == [], page.console.errors
    assert len(page.console.errors) == 1


def test_garment_layer_order_is_shown_and_reorderable(page):
    page.check("#garment-list input[data-id='jacket']")
    assert page.inner_text("#layer-order") == "T-shirt → Jacket" and page.is_hidden("#layer-warning")
    page.click("#garment-list li:has(input[data-id='jacket']) button[title='inward']")  # above the T-shirt
    assert page.inner_text("#layer-order") == "Jacket → T-shirt"
    assert "Jacket (layer 2) is listed inside T-shirt (layer 1)" in page.inner_text("#layer-warning")
    assert page.console.errors == []



@pytest.fixture(scope="module")
def keyed_url(tmp_path_factory):
    """A deployment with API keys and a synchronous frame limit of 20."""
    with _serve(tmp_path_factory.mktemp("keyed-jobs"), TRYON_API_KEYS="viewer-key", TRYON_MAX_FRAMES="20") as url:
        yield url


def _enter_key(page, key: str) -> None:
    page.fill("#api-key", key)
    page.press("#api-key", "Enter")


def test_with_api_keys_the_page_loads_and_sends_the_key(browser, keyed_url):
    page = _open(browser, keyed_url)  # the page and its files need no key
    assert page.is_visible("#api-key") and "API key (X-API-Key)" in page.inner_text("#status-text")
    _enter_key(page, "not-the-key")
    page.wait_for_selector("#problem:not([hidden])")
    assert "Forbidden (403)" in page.inner_text("#problem")
    _enter_key(page, "viewer-key")
    page.wait_for_function("document.querySelector('#garment-list').children.length > 0")
    assert page.is_hidden("#problem")
    page.check("input[name='body-mode'][value='measurements']")
    with page.expect_response("**/v1/bodies/fit") as fitted:  # a POST with the key
        page.click("#fit")
    assert fitted.value.status == 200
    page.wait_for_selector("#fit-result table")
    assert "phenotype" in page.inner_text("#fit-result")
    # Chromium's lines for the 403s of the wrong key (the catalog GETs), nothing else
    assert [e for e in page.console.errors if "status of 403" not in e] == [], page.console.errors
    page.close()


def test_a_drape_refused_as_too_long_falls_back_to_a_job(browser, keyed_url):
    page = browser.new_page(viewport=VIEWPORT)
    page.console = Console(page)

    def unknown_limit(route):  # the page does not know the limit, so it tries POST /v1/drape first
        config = route.fetch().json()
        route.fulfill(json={**config, "max_frames": 10_000})

    page.route("**/viewer/config.json", unknown_limit)
    page.goto(keyed_url + "/viewer")
    page.wait_for_function("document.querySelector('#status').dataset.state !== 'loading'")
    _enter_key(page, "viewer-key")
    page.wait_for_function("document.querySelector('#garment-list').children.length > 0")
    page.fill("#duration-s", "1")  # 31 frames, past the deployment's 20
    with page.expect_response("**/v1/drape") as refused, page.expect_response("**/v1/jobs") as accepted:
        page.click("#drape")
    assert refused.value.status == 422 and "/v1/jobs" in refused.value.text()
    assert accepted.value.status == 202
    _wait_ready(page)
    answer = _rows(page, "Answer")
    assert answer["route"].startswith("POST /v1/jobs") and answer["X-Frames"] == "31", answer
    assert [e for e in page.console.errors if "status of 422" not in e] == [], page.console.errors
    page.close()


def test_a_meshopt_compressed_glb_loads_and_draws(page, service_url):
    """EXT_meshopt_compression (options.compression): the page's GLTFLoader has the MeshoptDecoder."""
    probe = httpx.post(service_url + "/v1/drape", json={"motion": {"type": "clip", "clip": "walk", "duration_s": 0.1}, "garments": [{"id": "tshirt"}],
                                                        "format": "glb", "options": {"compression": "meshopt"}}, timeout=60)
    if probe.status_code != 200:
        pytest.skip(f"this service writes no meshopt glb (the 'compress' extra): {probe.text[:200]}")
    page.fill("#duration-s", "0.5")
    page.select_option("#compression", "meshopt")
    page.click("#drape")
    _wait_ready(page)
    answer = _rows(page, "Answer")
    assert "EXT_meshopt_compression" in answer["glTF extensions"] and answer["X-Frames"] == "16", answer
    assert _rows(page, "Options")["compression"] == "meshopt"
    page.click("#play")
    _scrub(page, 0.2)
    dressed = _canvas(page)
    _show(page, "tshirt", False)
    undressed = _canvas(page)
    _show(page, "body", False)
    empty = _canvas(page)
    figure, shirt = _changed(dressed, empty), _changed(dressed, undressed)
    assert figure.mean() > 0.06 and shirt.sum() > 0.15 * figure.sum(), (figure.mean(), shirt.sum() / figure.sum())
    assert page.console.errors == [], page.console.errors
