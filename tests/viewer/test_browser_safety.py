"""The viewer in headless Chromium against hostile input and with the keyboard: a crafted bundle.json cannot run
script in the page, `?bundle=` loads nothing from another origin, `[` `]` step through the cameras, and the
shortcuts work after a panel control was clicked and with Shift held.

No training: a small random textured model (tests/viewer/viewer_models.py) in a bundle with three cameras; a few
seconds of software WebGL per page load.
"""

from __future__ import annotations

import json
import os
import sys
import threading
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import quote

import pytest

from ctgs.formats.web_bundle import BUNDLE_JSON, write_web_bundle
from ctgs.viewer.server import ViewerServer
from viewer_models import camera, textured_model

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "benchmarks"))  # the headless-browser libraries of the benchmarks
from headless import Browser, BrowserError, find_chromium  # noqa: E402
from viewer_page import PANEL_CSS_PX, READY_TIMEOUT_S  # noqa: E402

pytestmark = pytest.mark.skipif(
    find_chromium() is None,
    reason="no Chromium to drive (Debian: apt-get install -y chromium, which .ci/run does; or set CTGS_CHROMIUM)")

# Script that sets window.__pwned when it runs: what a crafted bundle.json would smuggle into the page.
PAYLOAD = '<img src="x" onerror="window.__pwned = 1">'
EYES = [(0.3, -0.2, -2.6), (1.2, -0.3, -2.3), (-1.1, -0.1, -2.4)]


def _cameras() -> list[dict]:
    cams = []
    for i, eye in enumerate(EYES):
        c = camera(64, 48, eye)
        cams.append({"name": f"{i:03d}.png", "split": "test" if i == 0 else "train", "width": c.width,
                     "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "near": c.near,
                     "viewmat": [float(v) for v in c.viewmat.flatten()]})
    return cams


@pytest.fixture(scope="module")
def bundles(tmp_path_factory) -> dict:
    """A plain bundle (three cameras) and a crafted one whose text fields carry HTML (float16 texels, so the
    pages still decode whatever texel_format says, and the page gets as far as showing the fields)."""
    root = tmp_path_factory.mktemp("viewer_safety")
    plain, crafted = str(root / "plain"), str(root / "crafted")
    write_web_bundle(textured_model(n=40), plain, _cameras())
    write_web_bundle(textured_model(n=40), crafted, _cameras(), texel_bits=16)
    path = os.path.join(crafted, BUNDLE_JSON)
    bundle = json.load(open(path))
    bundle["atlas"]["texel_format"] = PAYLOAD
    bundle["cameras"][1]["name"] = PAYLOAD
    with open(path, "w") as f:
        json.dump(bundle, f)
    return {"plain": plain, "crafted": crafted}


@pytest.fixture(scope="module")
def browser():
    with Browser() as b:
        b.set_viewport(PANEL_CSS_PX + 640, 480)
        b.page("Log.enable")  # Content-Security-Policy violations come as log entries
        yield b


def _open(browser: Browser, url: str) -> None:
    browser.goto(url)
    browser.evaluate("window.viewer.ready.then(() => true)", timeout=READY_TIMEOUT_S)


def test_a_crafted_bundle_is_shown_as_text_and_runs_no_script(browser, bundles):
    with ViewerServer(bundles["crafted"]) as server:
        _open(browser, server.url)
        browser.evaluate("new Promise(r => setTimeout(r, 300))")  # an injected <img> would have fired onerror
        assert browser.evaluate("window.__pwned === undefined")
        assert browser.evaluate("document.querySelectorAll('#panel img').length") == 0
        stats = browser.evaluate("document.getElementById('stats').textContent")
        assert PAYLOAD in stats  # shown literally, as text
        options = browser.evaluate("[...document.querySelectorAll('#camera option')].map(o => o.textContent)")
        assert any(PAYLOAD in o for o in options)
        # the page works within its Content-Security-Policy: nothing of its own was refused
        assert browser.log_entries("security") == []


def test_the_page_runs_no_inline_script_even_if_html_got_in(browser, bundles):
    # defence in depth (the server's Content-Security-Policy): markup that reached the page by any path stays inert
    with ViewerServer(bundles["plain"]) as server:
        _open(browser, server.url)
        assert browser.log_entries("security") == []
        browser.evaluate(f"document.body.insertAdjacentHTML('beforeend', {json.dumps(PAYLOAD)}); "
                         "new Promise(r => setTimeout(r, 300))")
        assert browser.evaluate("window.__pwned === undefined")
        assert any("Content Security Policy" in line for line in browser.log_entries("security"))


class _CorsHandler(SimpleHTTPRequestHandler):
    """Another origin that allows any page to read it (as an attacker's server would)."""

    requests: list[str] = []

    def end_headers(self):
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def do_GET(self):
        _CorsHandler.requests.append(self.path)
        super().do_GET()

    def log_message(self, *args):
        pass


def test_bundle_parameter_is_limited_to_the_serving_origin(browser, bundles):
    other = ThreadingHTTPServer(("127.0.0.1", 0), partial(_CorsHandler, directory=os.path.dirname(bundles["crafted"])))
    thread = threading.Thread(target=other.serve_forever, daemon=True)
    thread.start()
    try:
        foreign = f"http://127.0.0.1:{other.server_address[1]}/crafted"
        with ViewerServer(bundles["plain"]) as server:
            for param in (foreign, "//127.0.0.1:%d/crafted" % other.server_address[1]):
                _CorsHandler.requests.clear()
                browser.goto(server.url + "?bundle=" + quote(param, safe=""))
                with pytest.raises(BrowserError, match="only loads bundles served by its own server"):
                    browser.evaluate("window.viewer.ready.then(() => true)", timeout=60)
                assert _CorsHandler.requests == [], "the page fetched from another origin"
                assert "only loads bundles" in browser.evaluate("document.getElementById('error').textContent")
                assert browser.evaluate("window.__pwned === undefined")
            # a folder on the serving origin still works
            _open(browser, server.url + "?bundle=bundle")
            assert browser.evaluate("window.viewer.info().cameras") == len(EYES)
    finally:
        other.shutdown()
        other.server_close()


def _cam(browser: Browser) -> int:
    return browser.evaluate("window.viewer.camIndex")


def test_bracket_keys_step_through_the_cameras(browser, bundles):
    with ViewerServer(bundles["plain"]) as server:
        _open(browser, server.url + "?camera=0")
        assert _cam(browser) == 0
        browser.press("]")
        assert _cam(browser) == 1
        browser.press("]")
        assert _cam(browser) == 2
        browser.press("]")
        assert _cam(browser) == 0  # wraps
        browser.press("[")
        assert _cam(browser) == 2
        assert browser.evaluate("document.getElementById('camera').value") == "2"
        assert not browser.page_errors(), browser.page_errors()


def _click(browser: Browser, element_id: str) -> None:
    x, y = browser.evaluate(f"(() => {{ const r = document.getElementById('{element_id}').getBoundingClientRect(); "
                            "return [r.x + r.width / 2, r.y + r.height / 2]; })()")
    browser.mouse_drag(x, y, x, y, steps=1)


def test_shortcuts_work_after_clicking_a_control_and_with_shift(browser, bundles):
    with ViewerServer(bundles["plain"]) as server:
        _open(browser, server.url + "?camera=0")
        textures = lambda: browser.evaluate("window.viewer.textures")  # noqa: E731
        mode = lambda: browser.evaluate("window.viewer.controls.mode")  # noqa: E731
        _click(browser, "textures")  # the checkbox now has the focus (and was toggled by the click)
        assert browser.evaluate("document.activeElement.id") == "textures"
        after_click = textures()
        browser.press("t")
        assert textures() is (not after_click)
        browser.press("T", shift=True)
        assert textures() is after_click
        assert mode() == "orbit"
        browser.press("F", shift=True)
        assert mode() == "fly"
        browser.press("f")
        assert mode() == "orbit"
        # the camera list focused: ] steps the camera (not the list's type-ahead), and the list follows
        browser.evaluate("document.getElementById('camera').focus()")
        browser.press("]")
        assert _cam(browser) == 1 and browser.evaluate("document.getElementById('camera').value") == "1"
        assert not browser.page_errors(), browser.page_errors()

