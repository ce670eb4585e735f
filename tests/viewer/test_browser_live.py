"""`ctgs view RUN_DIR` in a real browser (headless Chromium, software WebGL2) while `ctgs train` writes the run folder:
the page draws each newer checkpoint as it lands, keeps the camera, shows the run's progress, and ends on the
finished model, pixel for pixel `ctgs render`'s; its texel maps are `ctgs render --maps texels`'s; a camera path saved
from the page renders with `ctgs render --path FILE`.

One small training (a 64x48 demo scene, 16 views, `fast`, checkpoints every 1.5 s) runs beside the page, ~30 s.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.io.images import read_rgb
from ctgs.viewer.live import LiveRun
from ctgs.viewer.server import ViewerServer
from viewer_models import psnr

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))  # the headless-browser libraries of the benchmarks
from headless import Browser, find_chromium  # noqa: E402
from viewer_page import ViewerPage  # noqa: E402

pytestmark = pytest.mark.skipif(
    find_chromium() is None,
    reason="no Chromium to drive (Debian: apt-get install -y chromium, which .ci/run does; or set CTGS_CHROMIUM)")

DEMO_SCENE = ["--width", "64", "--height", "48", "--views", "16", "--points", "800"]
ITERATIONS = "800"
# Browser against `ctgs render`, per view (tests/viewer/test_browser.py's goal), for images and maps alike.
MIN_VIEW_PSNR = 35.0
# Two models of the run a few hundred iterations apart draw visibly different images (mean |difference| per channel).
MIN_CHANGE = 0.005
STARTUP_S = 300.0  # a training's start-up (the renderer extension loads, or builds on a first use)


def _cli(*args) -> None:
    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    assert result.exit_code == 0, result.output


def _wait(what: str, check, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A training started in the background, its run folder followed by the viewer's server, a page open on it."""
    root = tmp_path_factory.mktemp("live")
    scene, run = root / "scene", root / "run"
    _cli("demo-scene", scene, *DEMO_SCENE)
    log = open(root / "train.log", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "ctgs", "train", str(scene), "-o", str(run), "--preset", "fast", "--iterations",
         ITERATIONS, "-q", "--set", "threads=1", "--set", "checkpoint_first_s=0.5", "--set", "checkpoint_every_s=1.5"],
        cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": ROOT}, stdout=log, stderr=subprocess.STDOUT)
    work = root / "work"
    work.mkdir()
    try:
        _wait("the run folder", lambda: (run / "config.toml").exists(), STARTUP_S)
        with ViewerServer(live=LiveRun(str(run), str(work))) as server, Browser() as browser:
            browser.page("Log.enable")  # Content-Security-Policy violations come as log entries
            # at the cameras' image size (?fit=1): small draws, so the page draws each newer model soon (viewer.js pace())
            page = ViewerPage(browser, server.url + "?fit=1")  # ready once the first checkpoint is drawn
            yield {"run": str(run), "proc": proc, "page": page, "browser": browser, "root": root}
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait()
        log.close()


def _test_camera(browser) -> tuple[int, dict]:
    i = browser.evaluate("window.viewer.cameras.findIndex((c) => c.split === 'test')")
    assert i >= 0
    return i, browser.evaluate(f"window.viewer.cameras[{i}]")


def test_the_page_draws_each_newer_model_while_the_run_trains(session):
    page, browser, proc = session["page"], session["browser"], session["proc"]
    info = page.info
    assert info["live"] and info["modelVersion"] >= 1
    i, cam = _test_camera(browser)
    page.fit_viewport(cam["width"], cam["height"])
    before = page.capture(i)
    first = browser.evaluate("window.viewer.info()")
    version = browser.evaluate(f"window.viewer.waitModel({first['modelVersion']})", timeout=120)
    after = page.capture(i)
    second = browser.evaluate("window.viewer.info()")
    assert version > first["modelVersion"] and second["modelIteration"] > first["modelIteration"]
    assert browser.evaluate("window.viewer.bundle.live.source") == "checkpoints/last.pt", "the run ended first"
    assert proc.poll() is None  # drawn while the run was training
    change = float(np.abs(after - before).mean())
    assert change > MIN_CHANGE, f"the drawn model did not change ({change:.4f})"
    # the run's progress: its iteration, loss and time left from the log, as the panel shows them
    status = browser.evaluate("window.viewer.live")
    assert status["state"] == "training" and status["iteration"] >= second["modelIteration"]
    assert status["planned"] == int(ITERATIONS) and status["seconds_left"] is not None and status["loss"] > 0
    text = browser.evaluate("document.getElementById('run-stats').textContent")
    assert f"/ {int(ITERATIONS)}" in text and "time left" in text and "shown: iteration" in text
    assert not browser.page_errors(), browser.page_errors()
    assert browser.log_entries("security") == []


def test_the_finished_run_is_drawn_as_ctgs_render_draws_it(session, tmp_path):
    page, browser, proc = session["page"], session["browser"], session["proc"]
    assert proc.wait(timeout=600) == 0, open(session["root"] / "train.log").read()[-2000:]
    _wait("the page to show the finished model",
          lambda: browser.evaluate("window.viewer.live.state === 'finished' && !window.viewer.reloading && "
                                   "window.viewer.bundle.live.source === 'model.pt'"), 60)
    browser.evaluate("window.viewer.waitModel(0)")  # sorted and ready to draw
    assert browser.evaluate("window.viewer.live.seconds_left") == 0
    _cli("render", session["run"], "-o", tmp_path / "r", "--maps", "rgb,texels")
    i, cam = _test_camera(browser)
    page.fit_viewport(cam["width"], cam["height"])
    stem = os.path.join(tmp_path, "r", os.path.splitext(cam["name"])[0])
    for view_map, suffix in (("image", ".png"), ("texel_size", ".texels.png"), ("texture_res", ".texres.png")):
        rect = browser.evaluate(f"window.viewer.show({json.dumps({'camera': i, 'map': view_map})})")
        from viewer_page import decode_png

        shot = decode_png(browser.screenshot({"x": rect["x"], "y": rect["y"], "width": rect["imageWidth"],
                                              "height": rect["imageHeight"]}))
        ref = read_rgb(stem + suffix)
        assert shot.shape == ref.shape
        assert psnr(shot, ref) >= MIN_VIEW_PSNR, (view_map, psnr(shot, ref))
    assert not browser.page_errors(), browser.page_errors()


def test_a_camera_path_saved_from_the_page_renders_with_ctgs_render(session, tmp_path):
    page, browser = session["page"], session["browser"]
    session["proc"].wait(timeout=600)
    i, cam = _test_camera(browser)
    page.fit_viewport(cam["width"], cam["height"])
    shot = page.capture(i)  # the keyframes: this camera's view, then two more cameras'
    browser.evaluate(f"window.viewer.setCamera({i}); window.viewer.addKeyframe(); window.viewer.setCamera(3); "
                     "window.viewer.addKeyframe(); window.viewer.setCamera(9); window.viewer.addKeyframe()")
    browser.evaluate("document.getElementById('path-seconds').value = '1'; "
                     "document.getElementById('path-fps').value = '10'")
    path = browser.evaluate("window.viewer.cameraPath()")
    assert len(path["keyframes"]) == 3 and len(path["camera_path"]) == 10 and path["fps"] == 10
    assert (path["render_width"], path["render_height"]) == (cam["width"], cam["height"])
    assert math.isclose(path["camera_path"][0]["fov"], 2 * math.degrees(math.atan(cam["height"] / 2 / cam["fy"])),
                        rel_tol=1e-6)
    file = tmp_path / "camera_path.json"
    file.write_text(json.dumps(path))
    _cli("render", session["run"], "--path", file, "-o", tmp_path / "path.mp4", "--codec", "mpeg4")
    cv2 = pytest.importorskip("cv2")
    cap = cv2.VideoCapture(str(tmp_path / "path.mp4"))
    frames = []
    while (got := cap.read())[0]:
        frames.append(got[1][:, :, ::-1].astype(np.float32) / 255.0)
    assert len(frames) == 10
    # frame 0 is the first keyframe's view (through the codec: a lower bar than the lossless PNGs)
    assert psnr(frames[0], shot) >= 28.0 and psnr(frames[-1], shot) < 25.0
    # the page's own playback follows the same path and ends on the last keyframe
    browser.evaluate("window.viewer.playPath()")
    _wait("the playback to end", lambda: browser.evaluate("window.viewer.playing === null"), 30)
    last = path["camera_path"][-1]["camera_to_world"]
    pos = browser.evaluate("window.viewer.pose.pos")
    assert np.allclose(pos, [last[3], last[7], last[11]], atol=1e-6)
    assert not browser.page_errors(), browser.page_errors()
