"""Drive a headless Chromium over the DevTools protocol (CDP), standard library only.

Why this and not Playwright or `chromium --screenshot`: `--screenshot` fires at the load event, before
the viewer has fetched its bundle, sorted in its worker and drawn, and gives no way to read the page's
state (was WebGL2 there at all?). Playwright's Python package downloads its own browser (not possible
offline) and pulls Node. CDP over `--remote-debugging-pipe` needs no websocket library: the browser
reads NUL-terminated JSON messages on fd 3 and writes them on fd 4. That is all the tests need:
navigate, evaluate JavaScript (awaiting the viewer's promises) and capture a PNG screenshot.

A library of the benchmarks (viewer_bench.py, spark_view.py) and of the browser tests, which put benchmarks/ on
their sys.path.
"""

from __future__ import annotations

import base64
import json
import os
import select
import shutil
import subprocess
import tempfile
import time

# Debian's package; `chromium` on PATH is tried first.
CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "/usr/bin/chromium")
# Flags that work headless as root, with no network and no GPU. SwiftShader is the software GL that
# gives headless Chromium WebGL2 without a GPU (--enable-unsafe-swiftshader: recent Chromium refuses it
# for WebGL otherwise). --disable-gpu is deliberately absent: it would turn WebGL off.
BASE_FLAGS = (
    "--headless", "--no-sandbox", "--disable-quic", "--no-first-run", "--no-default-browser-check",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-extensions", "--disable-default-apps", "--mute-audio", "--hide-scrollbars",
    "--force-color-profile=srgb", "--disable-dev-shm-usage",
)
SOFTWARE_GL_FLAGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist")
GPU_FLAGS = ("--use-angle=vulkan", "--enable-features=Vulkan", "--ignore-gpu-blocklist")


class BrowserError(RuntimeError):
    """The browser could not be started, crashed, or a CDP command failed."""


def find_chromium() -> str | None:
    """Path of a Chromium executable, or None."""
    env = os.environ.get("CTGS_CHROMIUM")
    if env:
        return env if os.path.isfile(env) else None
    for name in CHROMIUM_CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """One headless Chromium with one page, controlled through CDP on a pipe.

    Use as a context manager. `gpu=False` (default) forces SwiftShader software GL.
    """

    def __init__(self, executable: str | None = None, *, gpu: bool = False, timeout: float = 120.0,
                 extra_flags: tuple[str, ...] = ()):
        exe = executable or find_chromium()
        if exe is None:
            raise BrowserError("no Chromium found: install it (Debian: apt-get install -y chromium) or set "
                               "CTGS_CHROMIUM=/path/to/chromium")
        self.timeout = timeout
        self._profile = tempfile.mkdtemp(prefix="ctgs-chromium-")
        self._next_id = 0
        self._buf = b""
        self._events: list[dict] = []
        # Our ends: write to the browser's fd 3, read from its fd 4.
        to_child_r, self._w = os.pipe()
        self._r, from_child_w = os.pipe()

        def wire_fds() -> None:  # in the child, before exec: put the pipe ends on fds 3 and 4
            a, b = os.dup(to_child_r), os.dup(from_child_w)  # fresh numbers, never 3 or 4 clashes
            os.dup2(a, 3)
            os.dup2(b, 4)
            os.set_inheritable(3, True)
            os.set_inheritable(4, True)

        flags = list(BASE_FLAGS) + list(GPU_FLAGS if gpu else SOFTWARE_GL_FLAGS) + list(extra_flags)
        self._log = open(os.path.join(self._profile, "chromium.log"), "w+b")
        self.proc = subprocess.Popen(
            [exe, *flags, "--remote-debugging-pipe", f"--user-data-dir={self._profile}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT, preexec_fn=wire_fds,
            close_fds=False, start_new_session=True,
        )
        os.close(to_child_r)
        os.close(from_child_w)
        try:
            targets = self.send("Target.getTargets")["targetInfos"]
            page = next((t for t in targets if t["type"] == "page"), None)
            target_id = page["targetId"] if page else self.send("Target.createTarget", url="about:blank")["targetId"]
            self.session = self.send("Target.attachToTarget", targetId=target_id, flatten=True)["sessionId"]
            self.page("Page.enable")
            self.page("Runtime.enable")
        except BaseException:
            self.close()
            raise

    # ---- protocol --------------------------------------------------------------------------------
    def _read_message(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError(f"no answer from Chromium within {self.timeout:.0f} s")
            ready, _, _ = select.select([self._r], [], [], min(left, 1.0))
            if not ready:
                if self.proc.poll() is not None:
                    raise BrowserError(f"Chromium exited (code {self.proc.returncode}): {self.log_tail()}")
                continue
            chunk = os.read(self._r, 1 << 20)
            if not chunk:
                raise BrowserError(f"Chromium closed the DevTools pipe: {self.log_tail()}")
            self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def send(self, method: str, session: str | None = None, timeout: float | None = None, **params) -> dict:
        """Send one CDP command and wait for its result (events seen meanwhile are kept in order)."""
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        data = json.dumps(msg).encode() + b"\0"
        while data:
            data = data[os.write(self._w, data):]
        deadline = time.monotonic() + (timeout or self.timeout)
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error'].get('message')} {reply['error'].get('data', '')}")
                return reply.get("result", {})
            if "method" in reply:
                self._events.append(reply)

    def page(self, method: str, timeout: float | None = None, **params) -> dict:
        return self.send(method, session=self.session, timeout=timeout, **params)

    # ---- conveniences ------------------------------------------------------------------------------
    def set_viewport(self, width: int, height: int) -> None:
        """CSS viewport of width x height at device pixel ratio 1 (one CSS pixel = one image pixel)."""
        self.page("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def goto(self, url: str) -> None:
        self._events.clear()
        self.page("Page.navigate", url=url)
        self.wait_event("Page.loadEventFired")

    def wait_event(self, method: str, timeout: float | None = None) -> dict:
        deadline = time.monotonic() + (timeout or self.timeout)
        while True:
            for i, ev in enumerate(self._events):
                if ev["method"] == method:
                    return self._events.pop(i)["params"]
            self._events.append(self._read_message(deadline))

    def evaluate(self, expression: str, timeout: float | None = None):
        """Evaluate JavaScript (promises awaited); returns its JSON value or raises with the JS error."""
        res = self.page("Runtime.evaluate", timeout=timeout, expression=expression, awaitPromise=True,
                        returnByValue=True)
        if "exceptionDetails" in res:
            det = res["exceptionDetails"]
            text = det.get("exception", {}).get("description") or det.get("text")
            raise BrowserError(f"JavaScript error: {text}")
        return res["result"].get("value")

    def screenshot(self, clip: dict | None = None) -> bytes:
        """PNG bytes of the viewport, or of clip = {x, y, width, height} (CSS pixels, scale 1)."""
        params: dict = {"format": "png", "captureBeyondViewport": False}
        if clip is not None:
            params["clip"] = {**clip, "scale": 1}
        return base64.b64decode(self.page("Page.captureScreenshot", **params)["data"])

    def page_errors(self) -> list[str]:
        """Uncaught JavaScript exceptions seen so far (since the last goto)."""
        return [ev["params"]["exceptionDetails"].get("exception", {}).get("description")
                or ev["params"]["exceptionDetails"].get("text", "")
                for ev in self._events if ev["method"] == "Runtime.exceptionThrown"]

    def mouse_drag(self, x0: float, y0: float, x1: float, y1: float, steps: int = 5, button: str = "left") -> None:
        """Press at (x0, y0), move in `steps` steps to (x1, y1), release (CSS pixels)."""
        self.page("Input.dispatchMouseEvent", type="mousePressed", x=x0, y=y0, button=button, clickCount=1)
        for k in range(1, steps + 1):
            x, y = x0 + (x1 - x0) * k / steps, y0 + (y1 - y0) * k / steps
            self.page("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y, button=button)
        self.page("Input.dispatchMouseEvent", type="mouseReleased", x=x1, y=y1, button=button, clickCount=1)

    def key(self, key: str, kind: str, *, shift: bool = False) -> None:
        """kind: "keyDown" or "keyUp" of a printable key such as "w" or "]" (shift: with Shift held; pass the
        shifted character, e.g. "T")."""
        code = f"Key{key.upper()}" if key.isalpha() else {"[": "BracketLeft", "]": "BracketRight"}.get(key, "")
        self.page("Input.dispatchKeyEvent", type=kind, key=key, text=key if kind == "keyDown" else "", code=code,
                  modifiers=8 if shift else 0)

    def press(self, key: str, *, shift: bool = False) -> None:
        """keyDown then keyUp of `key`."""
        self.key(key, "keyDown", shift=shift)
        self.key(key, "keyUp", shift=shift)

    def log_entries(self, source: str | None = None) -> list[str]:
        """The browser's own log lines since the last goto (e.g. source "security": Content-Security-Policy
        violations), once `self.page("Log.enable")` has been sent."""
        return [ev["params"]["entry"].get("text", "") for ev in self._events if ev["method"] == "Log.entryAdded"
                and (source is None or ev["params"]["entry"].get("source") == source)]

    def console_messages(self) -> list[str]:
        return [" ".join(str(a.get("value", a.get("description", ""))) for a in ev["params"].get("args", []))
                for ev in self._events if ev["method"] == "Runtime.consoleAPICalled"]

    def cpu_seconds(self) -> float:
        """CPU time (user + system) used so far by this browser's processes still alive (Linux /proc).

        With software GL the GPU process's CPU time is the rendering work itself: unlike wall time, it
        hardly depends on what else the machine runs, so it compares settings fairly on a busy machine.
        """
        ticks = os.sysconf("SC_CLK_TCK")
        total = 0
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[3]) == self.proc.pid:  # session id (the browser leads its own session)
                total += int(fields[11]) + int(fields[12])  # utime, stime
        return total / ticks

    def log_tail(self, n: int = 2000) -> str:
        try:
            self._log.flush()
            self._log.seek(0)
            return self._log.read().decode(errors="replace")[-n:].strip()
        except (OSError, ValueError):
            return ""

    def close(self) -> None:
        try:
            if self.proc.poll() is None:
                try:
                    self.send("Browser.close", timeout=5)
                except (BrowserError, OSError):
                    pass
                try:
                    self.proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
        finally:
            for fd in (self._r, self._w):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._log.close()
            shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> "Browser":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
