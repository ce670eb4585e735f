"""Screenshots and frame times of `ctgs view`'s page in headless Chromium (benchmarks/viewer_bench.py and the
browser tests of tests/viewer and tests/fusion; a library on their sys.path, beside headless.py)."""

from __future__ import annotations

import json

import cv2
import numpy as np

from headless import Browser, BrowserError

# Sidebar width of static/viewer.css: the viewport must hold the panel and the image side by side.
PANEL_CSS_PX = 260
# Loading the bundle (downloads, uploads, shader compilation, the first sort) in software GL.
READY_TIMEOUT_S = 600.0


def decode_png(png: bytes) -> np.ndarray:
    """PNG bytes -> [H, W, 3] float32 RGB in [0, 1]."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise BrowserError("the browser returned an undecodable screenshot")
    return img[:, :, ::-1].astype(np.float32) / 255.0


class ViewerPage:
    """One viewer page open in a headless browser (`browser`), at `url`."""

    def __init__(self, browser: Browser, url: str, *, width: int = 800, height: int = 600):
        self.browser = browser
        browser.set_viewport(PANEL_CSS_PX + width, height)
        browser.goto(url)
        try:
            browser.evaluate("window.viewer.ready.then(() => true)", timeout=READY_TIMEOUT_S)
        except BrowserError as exc:
            raise BrowserError(f"the viewer did not start: {exc}; console: {browser.console_messages()}") from exc
        self.info = browser.evaluate("window.viewer.info()")

    def fit_viewport(self, width: int, height: int) -> None:
        self.browser.set_viewport(PANEL_CSS_PX + width, max(height, 600))

    def capture(self, camera: int, textures: bool = True, size: tuple[int, int] | None = None, mesh: bool = False,
                shade: bool = True) -> np.ndarray:
        """Recorded camera `camera` at its image size (or resized to size = (W, H)) -> [H, W, 3] float32
        RGB screenshot of the canvas (mesh: of the mesh `ctgs view --mesh` shows, shaded or in its plain colours)."""
        opts = {"camera": camera, "textures": textures, "size": list(size) if size else None, "mesh": mesh,
                "shade": shade}
        rect = self.browser.evaluate(f"window.viewer.show({json.dumps(opts)})")
        w, h = rect["imageWidth"], rect["imageHeight"]
        if round(rect["width"]) != w or round(rect["height"]) != h:
            raise BrowserError(f"canvas is {rect['width']}x{rect['height']} CSS px, image {w}x{h}: "
                               "device pixel ratio is not 1")
        png = self.browser.screenshot({"x": rect["x"], "y": rect["y"], "width": w, "height": h})
        img = decode_png(png)
        if img.shape[:2] != (h, w):
            raise BrowserError(f"screenshot is {img.shape[1]}x{img.shape[0]}, expected {w}x{h}")
        return img

    def benchmark(self, camera: int, frames: int, textures: bool = True, size: tuple[int, int] | None = None,
                  tight: bool = True, timeout: float = 3600.0) -> dict:
        """Frame times of an orbit from recorded camera `camera` (see viewer.js benchmark())."""
        opts = {"camera": camera, "frames": frames, "textures": textures, "size": list(size) if size else None,
                "tight": tight}
        return self.browser.evaluate(f"window.viewer.benchmark({json.dumps(opts)})", timeout=timeout)
