"""The viewer in a real browser (headless Chromium, software WebGL2) against `ctgs render`, pixel by pixel.

A tiny demo model is trained here (300 iterations of the `fast` preset on a 96x72 demo scene, ~30 s),
exported with `ctgs export --format web`, rendered with `ctgs render`, opened in the viewer, and every
test camera is compared at its image size, with textures on and off.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.io.images import read_rgb, write_image
from ctgs.formats.web_bundle import read_bundle_json
from ctgs.viewer.server import ViewerServer
from viewer_models import psnr

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "benchmarks"))  # the headless-browser libraries of the benchmarks
from headless import Browser, BrowserError, find_chromium  # noqa: E402
from viewer_page import ViewerPage  # noqa: E402

pytestmark = pytest.mark.skipif(
    find_chromium() is None,
    reason="no Chromium to drive (Debian: apt-get install -y chromium, which .ci/run does; or set CTGS_CHROMIUM)")

# The goal for browser vs `ctgs render`, per view, textures on and off.
MIN_VIEW_PSNR = 35.0
# Textures on vs off must differ by more than a render mismatch could hide: the toggle test is only
# meaningful if ignoring the toggle would fail it by a margin (> 3 dB under the goal).
MAX_ON_OFF_PSNR = MIN_VIEW_PSNR - 3.0
DEMO_SCENE = ["--width", "96", "--height", "72", "--views", "24", "--points", "1500"]
DEMO_ITERATIONS = "300"


def _cli(*args: str) -> None:
    result = CliRunner().invoke(main, list(args), catch_exceptions=False)
    assert result.exit_code == 0, result.output


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> dict:
    """Tiny trained demo: run folder, web bundle, `ctgs render` PNGs (textures on) and textures-off PNGs."""
    from ctgs.runs import load_run
    from ctgs.render import render
    from ctgs.scene.loader import load_scene

    root = tmp_path_factory.mktemp("viewer_demo")
    scene, run, out = str(root / "scene"), str(root / "run"), str(root / "render")
    _cli("demo-scene", scene, *DEMO_SCENE)
    _cli("train", scene, "-o", run, "--preset", "fast", "--iterations", DEMO_ITERATIONS, "-q",
         "--set", "threads=1")
    _cli("export", run, "--format", "web")
    _cli("render", run, "-o", out)
    # Textures off: the same renderer with every texture dropped, through the same PNG path.
    r = load_run(run)
    r.model.texture_mode = "none"
    views = load_scene(r.scene_dir, images=r.images, holdout=r.holdout, load_images=False).test
    off = str(root / "render_off")
    os.makedirs(off)
    with torch.no_grad():
        inputs = r.model.render_inputs()
        for v in views:
            rgb = render(inputs, v.camera, backend="cpu", sh_degree=r.model.sh_degree).rgb
            write_image(os.path.join(off, os.path.splitext(v.name)[0] + ".png"), rgb.clamp(0, 1).numpy())
    web = os.path.join(run, "model", "web")
    return {"web": web, "on": out, "off": off, "bundle": read_bundle_json(web)}


@pytest.fixture(scope="module")
def page(demo):
    with ViewerServer(demo["web"]) as server, Browser() as browser:
        yield ViewerPage(browser, server.url)


def _test_cameras(bundle: dict) -> list[tuple[int, dict]]:
    cams = [(i, c) for i, c in enumerate(bundle["cameras"]) if c["split"] == "test"]
    assert cams, "the demo scene has no test cameras"
    return cams


def _compare(page: ViewerPage, demo: dict, textures: bool) -> dict[str, float]:
    table = {}
    for i, cam in _test_cameras(demo["bundle"]):
        page.fit_viewport(cam["width"], cam["height"])
        shot = page.capture(i, textures=textures)
        ref = read_rgb(os.path.join(demo["on" if textures else "off"], os.path.splitext(cam["name"])[0] + ".png"))
        assert shot.shape == ref.shape
        table[cam["name"]] = psnr(shot, ref)
    print(f"\nbrowser vs ctgs render, textures {'on' if textures else 'off'} (dB): "
          + ", ".join(f"{k} {v:.2f}" for k, v in table.items()))
    return table


def test_webgl2_really_renders(page, demo):
    info = page.info
    assert info["webgl2"] and info["glRenderer"], info
    assert info["accumFormat"] in ("RGBA32F", "RGBA16F"), info  # float blending, not 8-bit
    i, cam = _test_cameras(demo["bundle"])[0]
    page.fit_viewport(cam["width"], cam["height"])
    shot = page.capture(i)
    assert float(shot.std()) > 0.05, "the viewer's image is (nearly) constant: nothing was drawn"


def test_no_webgl2_fails_loudly(demo):
    # Without WebGL the page must say so (and the scripting interface reject), never show a black image.
    with ViewerServer(demo["web"]) as server, Browser(extra_flags=("--disable-webgl",)) as browser:
        with pytest.raises(BrowserError, match="WebGL2 is not available"):
            ViewerPage(browser, server.url)


def test_browser_matches_ctgs_render_per_test_view(page, demo):
    table = _compare(page, demo, textures=True)
    bad = {k: round(v, 2) for k, v in table.items() if not v >= MIN_VIEW_PSNR}
    assert not bad, f"views under {MIN_VIEW_PSNR} dB: {bad} (all: {table})"


def test_texture_toggle_matches_a_textures_off_render(page, demo):
    table = _compare(page, demo, textures=False)
    bad = {k: round(v, 2) for k, v in table.items() if not v >= MIN_VIEW_PSNR}
    assert not bad, f"textures off, views under {MIN_VIEW_PSNR} dB: {bad} (all: {table})"
    for _, cam in _test_cameras(demo["bundle"]):
        name = os.path.splitext(cam["name"])[0] + ".png"
        on_off = psnr(read_rgb(os.path.join(demo["on"], name)), read_rgb(os.path.join(demo["off"], name)))
        assert on_off <= MAX_ON_OFF_PSNR, f"{name}: textures on vs off only differ by {on_off:.1f} dB PSNR"


def test_screenshot_is_the_canvas_not_the_page(page, demo):
    # The clip must hold exactly the image: its first and last rows/columns are not the panel's colour.
    i, cam = _test_cameras(demo["bundle"])[-1]
    page.fit_viewport(cam["width"], cam["height"])
    shot = page.capture(i)
    ref = read_rgb(os.path.join(demo["on"], os.path.splitext(cam["name"])[0] + ".png"))
    for edge in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1]):
        assert np.abs(shot[edge] - ref[edge]).mean() < 0.02


def test_tight_quads_draw_exactly_the_image_of_bounds_h_pixel_boxes(page, demo):
    # The tight coverage quads (and the near-plane clipped boxes) must lose no fragment that the
    # conservative pixel boxes of the CPU tiler would draw: identical screenshots.
    for i, cam in _test_cameras(demo["bundle"]):
        page.fit_viewport(cam["width"], cam["height"])
        tight = page.capture(i)
        page.browser.evaluate("window.viewer.renderer.tightQuads = false")
        try:
            boxes = page.capture(i)
        finally:
            page.browser.evaluate("window.viewer.renderer.tightQuads = true")
        assert np.array_equal(tight, boxes), f"{cam['name']}: max diff {np.abs(tight - boxes).max() * 255:.0f}/255"


def test_controls_move_the_camera_and_a_camera_jump_restores_the_view(page, demo):
    browser = page.browser
    i, cam = _test_cameras(demo["bundle"])[0]
    page.fit_viewport(cam["width"], cam["height"])
    page.capture(i)
    pose = lambda: browser.evaluate("JSON.stringify(window.viewer.pose)")  # noqa: E731
    rect = browser.evaluate("(() => { const r = document.getElementById('canvas').getBoundingClientRect(); "
                            "return [r.x, r.y, r.width, r.height]; })()")
    cx, cy = rect[0] + rect[2] / 2, rect[1] + rect[3] / 2
    start = pose()
    browser.mouse_drag(cx, cy, cx + 20, cy + 5)  # orbit
    orbited = pose()
    assert orbited != start and browser.evaluate("window.viewer.camIndex") == -1
    browser.key("f", "keyDown")  # fly mode
    browser.key("f", "keyUp")
    assert browser.evaluate("window.viewer.controls.mode") == "fly"
    browser.key("w", "keyDown")
    browser.evaluate("new Promise(r => setTimeout(r, 300))")  # held for a few animation frames
    browser.key("w", "keyUp")
    assert pose() != orbited
    browser.key("f", "keyDown")
    browser.key("f", "keyUp")
    # back on the recorded camera: the same image as before any motion
    shot = page.capture(i)
    ref = read_rgb(os.path.join(demo["on"], os.path.splitext(cam["name"])[0] + ".png"))
    assert psnr(shot, ref) >= MIN_VIEW_PSNR
    assert not browser.page_errors(), browser.page_errors()
