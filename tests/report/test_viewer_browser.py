"""Issue #40 in a real browser: headless Chromium (Debian's ``chromium``, driven by Playwright's Python package with
``executable_path``; software WebGL2 through SwiftShader) opens the viewer from disk, snaps to a captured view
under the flash, and its canvas is compared with sellip's own renderer (:class:`sellip.render.Renderer`, one sample
per pixel centre, as the GPU rasterizes) at the same camera: PSNR over the object's pixels; the analyzer at 0 and
90 degrees against the renderer's I0 - I90; every map, AoLP, DoP and Mueller mode non-empty and in range; the value
under the cursor. Skipped when chromium or playwright is missing (``apt-get install chromium``; ``pip install
playwright``: no browser download needed).

By default on a results folder built from scene ``tiny`` (tests/viewer_helpers.py). On a finished run, e.g. the
demo: ``SELLIP_VIEWER_RESULTS=results/demo SELLIP_VIEWER_VIEW=v004 pytest tests/test_viewer_browser.py -s``
(its viewer/ is rewritten, with the capture that metrics.json names)."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from viewer_helpers import FLASH, write_results

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
BROWSER_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]
RESULTS = os.environ.get("SELLIP_VIEWER_RESULTS")
HELD_OUT = os.environ.get("SELLIP_VIEWER_VIEW", "v005")

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not shutil.which("chromium"),
                                                    reason="needs Debian's chromium (apt-get install chromium)")]


def srgb(linear: np.ndarray) -> np.ndarray:
    c = np.clip(linear, 0, 1)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / max(np.mean((a - b) ** 2), 1e-10)))


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    """(results folder, index.html, the flash of its capture)."""
    from sellip.report.viewer import find_capture, load_inputs, write_viewer

    if RESULTS:
        results = Path(RESULTS)
        inputs = load_inputs(results, find_capture(results))
    else:
        results = write_results(tmp_path_factory.mktemp("browser"))
        inputs = load_inputs(results)
        inputs.light = dict(FLASH)
    return results, write_viewer(results / "viewer", inputs), inputs.light


def camera_at(results: Path, view_id: str):
    """The captured camera ``view_id`` at the HDR grid's intrinsics (as the page snaps to it)."""
    import zarr

    from sellip.model.render import Camera
    from sellip.report.viewer import read_pose_table

    k = zarr.open_group(str(results / "hdr.zarr"), mode="r").attrs["intrinsics"]
    _, rotation, translation = next(c for c in read_pose_table(results / "cameras.csv") if c[0] == view_id)
    return Camera(np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1]]), rotation, translation,
                  int(k["width"]), int(k["height"]))


@pytest.fixture(scope="module")
def page(viewer):
    playwright = pytest.importorskip("playwright.sync_api")
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=BROWSER_ARGS)
        page = browser.new_page(viewport={"width": 1400, "height": 900}, device_scale_factor=1)
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(viewer[1].resolve().as_uri())
        page.wait_for_function("window.sellipViewer && (window.sellipViewer.ready || window.sellipViewer.error)",
                               timeout=120_000)
        assert page.evaluate("window.sellipViewer.error || null") is None and not errors, errors
        k = page.evaluate("window.sellipViewer.meta.intrinsics")
        page.evaluate(f"window.sellipViewer.setSize({int(k['width'])}, {int(k['height'])})")
        yield page
        browser.close()


def canvas(page) -> np.ndarray:
    """(H, W, 3) float in [0, 1] of the canvas as displayed."""
    import imageio.v3 as iio

    return iio.imread(page.locator("#view").screenshot())[..., :3].astype(np.float64) / 255


@pytest.fixture(scope="module")
def reference(viewer):
    """sellip's renderer at the held-out view under the flash: Stokes (H, W, 4, 3) and coverage."""
    from sellip.model.ply import read_param_mesh
    from sellip.model.render import Renderer, flash_light

    results, _, light = viewer
    mesh = read_param_mesh(results / "final" / "model.ply")
    camera = camera_at(results, HELD_OUT)
    render = Renderer(mesh).render(camera, flash_light(camera, light["position_m"], light["polarizer_deg"]),
                                   supersample=1, shadows=True)
    return render.stokes.astype(np.float64), render.coverage


def test_flash_view_matches_sellips_renderer(page, reference):
    stokes, coverage = reference
    mask = coverage > 0.5
    exposure = 1.0 / np.percentile(stokes[..., 0, :][mask], 99)
    page.evaluate(f"window.sellipViewer.snapToView('{HELD_OUT}')")
    page.evaluate(f"window.sellipViewer.set({{mode: 'relight', light: 'flash', exposure: {exposure}, srgb: true, "
                  f"useAnalyzer: false, frusta: false}})")
    shot = canvas(page)
    expected = srgb(exposure * stokes[..., 0, :])
    assert shot.shape == expected.shape
    value = psnr(shot[mask], expected[mask])
    print(f"viewer vs renderer at {HELD_OUT}: PSNR {value:.1f} dB over {mask.sum()} object pixels")
    assert mask.sum() > 2_000 and value >= 35.0
    # background black: no extra geometry (a few silhouette pixels may differ: float32 rasterization, ray casting)
    assert (shot[~mask].max(-1) >= 2 / 255).sum() < 0.002 * mask.sum()


def test_free_unpolarized_light_matches_the_renderers_mueller_path(page, viewer, reference):
    """A free point light, unpolarized: the page's Mueller block times (1, 0, 0) against the renderer's
    full_mueller with Light(stokes=(1, 0, 0, 0)), at the same light position."""
    from sellip.model.ply import read_param_mesh
    from sellip.model.render import Light, Renderer

    results = viewer[0]
    page.evaluate(f"window.sellipViewer.snapToView('{HELD_OUT}')")
    page.evaluate("window.sellipViewer.set({mode: 'relight', light: 'free', freePolarized: false, "
                  "free: {azimuth: 1.2, elevation: 0.6, distance: 0.5}, srgb: true, useAnalyzer: false})")
    light = page.evaluate("window.sellipViewer.light()")
    assert light["stokes"] == [1, 0, 0]
    camera = camera_at(results, HELD_OUT)
    render = Renderer(read_param_mesh(results / "final" / "model.ply")).render(
        camera, Light(np.array(light["position"]), np.array(light["axis"]), stokes=(1.0, 0.0, 0.0, 0.0)),
        supersample=1, shadows=True)
    mask = reference[1] > 0.5
    s0 = render.stokes[..., 0, :].astype(np.float64)
    exposure = 1.0 / np.percentile(s0[mask], 99)
    page.evaluate(f"window.sellipViewer.set({{exposure: {exposure}}})")
    value = psnr(canvas(page)[mask], srgb(exposure * s0)[mask])
    print(f"free unpolarized light: PSNR {value:.1f} dB")
    assert value >= 35.0
    page.evaluate("window.sellipViewer.set({light: 'flash'})")


def test_analyzer_0_minus_90_matches_the_renderers(page, reference):
    stokes, coverage = reference
    analyzers = 0.5 * (stokes[..., 0, :, None] + np.stack([stokes[..., 1, :], -stokes[..., 1, :]], -1))  # I0, I90
    mask = coverage > 0.5
    exposure = 0.8 / np.percentile(analyzers[mask], 99)
    inside = mask & np.all(exposure * analyzers < 0.99, axis=(-2, -1))  # neither clipped
    page.evaluate(f"window.sellipViewer.snapToView('{HELD_OUT}')")
    shots = []
    for angle in (0, 90):
        page.evaluate(f"window.sellipViewer.set({{mode: 'relight', light: 'flash', exposure: {exposure}, srgb: false, "
                      f"useAnalyzer: true, analyzer: {angle}}})")
        shots.append(canvas(page))
    difference = shots[0] - shots[1]
    expected = exposure * (analyzers[..., 0] - analyzers[..., 1])
    rmse = float(np.sqrt(np.mean((difference[inside] - expected[inside]) ** 2)))
    correlation = float(np.corrcoef(difference[inside].ravel(), expected[inside].ravel())[0, 1])
    print(f"I0 - I90: rmse {rmse * 255:.2f}/255, correlation {correlation:.4f}, over {inside.sum()} pixels")
    assert rmse < 2 / 255 and correlation > 0.99
    # 45 and 135 degrees: I45 - I135 = s2 (the angle grows from image x towards image up, docs/conventions.md)
    s2 = exposure * stokes[..., 2, :]
    inside45 = mask & np.all(exposure * 0.5 * (stokes[..., 0, :, None] + np.stack([s2, -s2], -1) / exposure) < 0.99,
                             axis=(-2, -1))
    shots = []
    for angle in (45, 135):
        page.evaluate(f"window.sellipViewer.set({{analyzer: {angle}}})")
        shots.append(canvas(page))
    rmse45 = float(np.sqrt(np.mean(((shots[0] - shots[1]) - s2)[inside45] ** 2)))
    d = (shots[0] - shots[1])[inside45]
    correlation45 = np.corrcoef(d.ravel(), s2[inside45].ravel())[0, 1]
    print(f"I45 - I135: rmse {rmse45 * 255:.2f}/255, correlation {correlation45:.4f}")
    assert rmse45 < 2 / 255 and np.abs(s2[inside45]).max() > 10 / 255  # a signal to compare (17/255 here)
    page.evaluate("window.sellipViewer.set({srgb: true, useAnalyzer: false})")


@pytest.mark.parametrize("mode,map_name", [("aolp", None), ("dop", None), ("mueller", None)] +
                         [("map", m) for m in ("eta", "rho_d", "rho_s", "sigma_s", "rho_ss", "sigma_ss", "normal",
                                               "confidence", "model", "cluster")])
def test_every_mode_draws_the_object(page, viewer, reference, mode, map_name):
    _, coverage = reference
    page.evaluate(f"window.sellipViewer.snapToView('{HELD_OUT}')")
    options = f"mode: '{mode}', light: 'flash'" + (f", map: '{map_name}'" if map_name else "")
    page.evaluate(f"window.sellipViewer.set({{{options}}})")
    shot = canvas(page)
    assert np.isfinite(shot).all() and shot.min() >= 0 and shot.max() <= 1
    if mode == "mueller":  # nine tiles: each shows the object
        h, w = shot.shape[0] // 3, shot.shape[1] // 3
        for i in range(3):
            for j in range(3):
                assert shot[i * h:(i + 1) * h, j * w:(j + 1) * w].max() > 0.2, (i, j)
        # mirror reflection at the highlight keeps s1 and flips s2: M11 / M00 ~ +1 (red), M22 / M00 ~ -1 (blue)
        tile = lambda i, j: shot[i * h:(i + 1) * h, j * w:(j + 1) * w]
        red = lambda t: (t[..., 0] > 0.8) & (t[..., 1] < 0.5) & (t[..., 2] < 0.5)
        blue = lambda t: (t[..., 2] > 0.8) & (t[..., 0] < 0.5) & (t[..., 1] < 0.5)
        if not RESULTS:  # the tiny sphere's glossy half has a highlight that the specular lobe dominates
            assert red(tile(1, 1)).sum() > 0 and blue(tile(2, 2)).sum() > 0 and not blue(tile(1, 1)).any()
        return
    mask = coverage > 0.5
    drawn = shot[mask].max(-1) > 0.02
    if map_name == "rho_ss":  # black where the model has no single scattering (the glossy half of the tiny sphere)
        from sellip.model.ply import read_ply

        vertex, _ = read_ply(viewer[0] / "final" / "model.ply")
        with_ss = float(np.mean(np.max([vertex[f"rho_ss_{c}"] for c in "rgb"], axis=0) > 0))
        assert (drawn.mean() > 0.3) if with_ss > 0.3 else (drawn.mean() < 0.01), (drawn.mean(), with_ss)
    else:  # AoLP/DoP are blank where dark
        assert drawn.mean() > (0.3 if mode in ("aolp", "dop") else 0.99), drawn.mean()
    if map_name == "eta":  # two materials: two colours, the low eta darker in viridis
        colors = np.unique(np.round(shot[mask] * 255).astype(int), axis=0)
        assert len(colors) >= 2
    page.evaluate("window.sellipViewer.set({mode: 'relight'})")


def test_value_under_the_cursor_names_the_vertex(page, reference):
    _, coverage = reference
    rows, cols = np.nonzero(coverage > 0.5)
    y, x = int(np.median(rows)), int(np.median(cols))
    page.evaluate(f"window.sellipViewer.snapToView('{HELD_OUT}')")
    page.evaluate("window.sellipViewer.set({light: 'flash'})")
    hit = page.evaluate(f"window.sellipViewer.pick({x}, {y})")
    assert hit is not None and re.search(r"η 1\.\d{3} .*± 0\.\d{3}", hit["text"]), hit
    # the pixel's Stokes vector: the renderer's, colour-averaged, at that pixel (float32 through the float target)
    stokes, _ = reference
    expected = stokes[y, x, :3, :].mean(-1)
    assert np.all(np.abs(np.array(hit["stokes"]) - expected) < 0.01 * expected[0]), (hit["stokes"], expected)
    assert "DoP" in hit["text"] and "AoLP" in hit["text"]
    if not RESULTS:
        assert "± 0.020" in hit["text"]  # eta_std of tests/viewer_helpers.py
    assert page.evaluate("window.sellipViewer.pick(2, 2)") is None  # background


def test_hovering_with_the_mouse_shows_the_vertex(page, reference):
    _, coverage = reference
    rows, cols = np.nonzero(coverage > 0.5)
    page.evaluate(f"window.sellipViewer.snapToView('{HELD_OUT}')")
    page.evaluate("window.sellipViewer.set({mode: 'map', map: 'eta'})")
    box = page.locator("#view").bounding_box()
    page.mouse.move(box["x"] + float(np.median(cols)) + 0.5, box["y"] + float(np.median(rows)) + 0.5)
    page.wait_for_function("document.getElementById('hover').textContent.includes('vertex ')", timeout=10_000)
    assert "cluster" in page.evaluate("document.getElementById('hover').textContent")
    assert page.evaluate("document.getElementById('mode-map').checked")  # the controls follow the state


def test_the_page_controls_drive_the_view(page):
    """Clicks, drags and the wheel as a user would: each changes the view or the state, and nothing throws."""
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.evaluate(f"window.sellipViewer.snapToView('{HELD_OUT}')")
    page.check("#mode-relight")
    before = canvas(page)
    box = page.locator("#view").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx + 60, cy + 10, steps=4)
    page.mouse.up()
    page.evaluate("window.sellipViewer.set({})")
    assert np.abs(canvas(page) - before).max() > 0.1  # orbited
    assert page.evaluate("window.sellipViewer.state().view") is None
    page.click("#reset")
    page.select_option("#view-select", HELD_OUT)
    page.evaluate("window.sellipViewer.set({})")  # draw now (the page itself draws at the next animation frame)
    assert np.abs(canvas(page) - before).max() < 2 / 255  # back at the captured view
    page.mouse.move(cx, cy)
    page.mouse.wheel(0, 400)
    page.wait_for_timeout(100)
    page.evaluate("window.sellipViewer.set({})")
    assert canvas(page).mean() < before.mean()  # zoomed out: the object covers fewer pixels
    page.select_option("#view-select", HELD_OUT)
    page.keyboard.down("Shift")
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx + 80, cy, steps=4)
    page.mouse.up()
    page.keyboard.up("Shift")
    assert page.evaluate("window.sellipViewer.state().light") == "free" and page.is_checked("#light-free")
    page.check("#light-flash")
    page.check("#frusta")
    page.select_option("#map-select", "sigma_s")
    assert page.evaluate("window.sellipViewer.state().mode") == "map" and page.is_checked("#mode-map")
    page.check("#mode-mueller")
    page.check("#analyzer-on")
    page.fill("#analyzer", "45")
    page.dispatch_event("#analyzer", "input")
    assert page.evaluate("window.sellipViewer.state().analyzer") == 45
    page.fill("#exposure", "1")
    page.dispatch_event("#exposure", "input")
    ratio = page.evaluate("window.sellipViewer.state().exposure / window.sellipViewer.meta.exposure")
    assert ratio == pytest.approx(2.0)
    page.wait_for_timeout(100)
    assert not errors, errors
    page.evaluate("window.sellipViewer.set({mode: 'relight', frusta: false, useAnalyzer: false, analyzer: 0, "
                  "light: 'flash'})")
