"""The viewer's static HTTP server: the page and its scripts from the package, the bundle from disk.

Bound to 127.0.0.1 only, and answering only requests addressed to it (the Host header: a page elsewhere cannot reach
it through DNS rebinding); a malformed path gets 400. Nothing is fetched from the internet: every script is in
ctgs/viewer/static.
URL layout: /  -> static/index.html and its assets; /bundle/<file> -> the web bundle folder, with
bundle.json's cameras replaced when the server was given other cameras (`ctgs view --scene`), and a mesh to show
beside the surfels (`ctgs view --mesh`) as /bundle/mesh.bin, from memory (bundle.json's `mesh` entry describes it).
A run folder followed while it trains (ctgs.viewer.live) instead: /live/status.json -> the run's progress and the
version of the newest model, /live/<version>/<file> -> that model's bundle; /bundle/ then answers 404, and in a bundle's
viewer /live/ does.
"""

from __future__ import annotations

import json
import mimetypes
import os
import re
import sys
import threading
from functools import partial
from http import HTTPStatus
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import unquote, urlsplit

from ctgs.formats.mesh import VIEWER_MESH_BIN
from ctgs.formats.web_bundle import BUNDLE_JSON, read_bundle_json

STATIC_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static")
HOST = "127.0.0.1"
# Types the page needs that Python's table may lack (module scripts must be served as JavaScript).
EXTRA_TYPES = {".js": "text/javascript", ".vert": "text/plain", ".frag": "text/plain", ".bin": "application/octet-stream",
               ".json": "application/json", ".css": "text/css", ".html": "text/html"}


CSP = ("default-src 'self'; script-src 'self'; connect-src 'self'; img-src 'self' data:; style-src 'self'; "
       "object-src 'none'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")


_LIVE_FILE = re.compile(r"^/live/(\d{1,9})/([^/]+)$")


class _Handler(SimpleHTTPRequestHandler):
    def __init__(self, *args, bundle_dir: str | None, bundle_json: bytes | None, quiet: bool,
                 mesh_bin: bytes | None = None, live=None, **kwargs):
        self.bundle_dir = bundle_dir
        self.bundle_json = bundle_json
        self.mesh_bin = mesh_bin
        self.live = live  # ctgs.viewer.live.LiveRun, or None
        self.quiet = quiet
        super().__init__(*args, directory=STATIC_DIR, **kwargs)

    def guess_type(self, path):
        ext = os.path.splitext(str(path))[1].lower()
        return EXTRA_TYPES.get(ext) or mimetypes.guess_type(str(path))[0] or "application/octet-stream"

    def end_headers(self):
        # The bundle and scripts change between exports: never let the browser reuse a stale copy.
        self.send_header("Cache-Control", "no-store")
        # Defence in depth: only this server's own scripts run (no inline script or handler, whatever a bundle
        # holds), nothing is fetched elsewhere, and no other site may frame the page.
        self.send_header("Content-Security-Policy", CSP)
        self.send_header("X-Content-Type-Options", "nosniff")
        super().end_headers()

    def _refused(self) -> bool:
        """Answer what the server must not serve; True when it answered. A Host other than this server's own
        (127.0.0.1:PORT or localhost:PORT) is a page elsewhere reaching it through DNS rebinding: refused. A path
        that cannot name a file (a NUL, bad percent escapes) gets 400, never a traceback in the user's terminal."""
        port = self.server.server_address[1]
        host = (self.headers.get("Host") or "").strip().lower()
        ours = {f"{HOST}:{port}", f"localhost:{port}"} | ({HOST, "localhost"} if port == 80 else set())
        if host not in ours:  # (a browser leaves out port 80)
            self.send_error(HTTPStatus.MISDIRECTED_REQUEST, "this viewer answers only to its own address")
            return True
        try:
            path = unquote(urlsplit(self.path).path, errors="strict")
        except (UnicodeDecodeError, ValueError):
            path = None
        if path is None or not path.startswith("/") or any(ord(ch) < 32 or ch == "\x7f" for ch in path) or "\\" in path:
            self.send_error(HTTPStatus.BAD_REQUEST, "malformed path")
            return True
        return False

    def translate_path(self, path):
        rel = unquote(urlsplit(path).path)
        if rel.startswith("/bundle/"):
            if self.bundle_dir is None:
                return os.path.join(STATIC_DIR, ".invalid")  # a run folder's viewer serves its models under /live/
            return _bundle_file(self.bundle_dir, rel[len("/bundle/"):])
        if rel.startswith("/live/"):
            m = _LIVE_FILE.match(rel)
            folder = self.live.bundle_dir(int(m.group(1))) if self.live is not None and m else None
            return _bundle_file(folder, m.group(2)) if folder else os.path.join(STATIC_DIR, ".invalid")
        return super().translate_path(path)

    def list_directory(self, path):
        self.send_error(HTTPStatus.NOT_FOUND, "no listings here")  # neither the bundle folder nor the page's own
        return None

    def do_HEAD(self):
        if self._refused():
            return
        super().do_HEAD()

    def do_GET(self):
        if self._refused():
            return
        path = urlsplit(self.path).path
        if path == "/live/status.json" and self.live is not None:
            data = json.dumps(self.live.status()).encode()
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)
            return
        if self.bundle_dir is not None and path == "/bundle/" + BUNDLE_JSON or (path == "/bundle/" + VIEWER_MESH_BIN and self.mesh_bin is not None):
            data, kind = ((self.bundle_json, "application/json") if path.endswith(BUNDLE_JSON)
                          else (self.mesh_bin, "application/octet-stream"))
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)
            return
        super().do_GET()

    def log_message(self, format, *args):
        if not self.quiet:
            super().log_message(format, *args)


def _bundle_file(folder: str, name: str) -> str:
    """folder/name when it is one of the bundle's own files; a name that serves 404 otherwise. A bundle is flat: its
    own files only, never a listing, a hidden file, or a link leading out of it."""
    target = os.path.join(folder, name)
    if not name or "/" in name or name.startswith(".") or not os.path.isfile(target) or \
            os.path.dirname(os.path.realpath(target)) != os.path.realpath(folder):
        return os.path.join(folder, ".invalid")
    return target


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):
        if isinstance(sys.exc_info()[1], (ConnectionError, TimeoutError)):
            return  # a client that went away before its answer was sent (a closed tab, a reload): nothing to say
        super().handle_error(request, client_address)


class ViewerServer:
    """Serves the viewer for one bundle folder, or for a run folder followed while it trains (live: a
    ctgs.viewer.live.LiveRun; bundle_dir None). port=0 picks a free port. Use as a context manager or call
    serve_forever(); `url` is the page's address."""

    def __init__(self, bundle_dir: str | None = None, *, port: int = 0, cameras: list[dict] | None = None,
                 quiet: bool = True, mesh: tuple[dict, bytes] | None = None, live=None):
        if (bundle_dir is None) == (live is None):
            raise ValueError("serve a bundle folder or a live run, one of them")
        bundle_json = None
        if bundle_dir is not None:
            bundle = read_bundle_json(bundle_dir)  # UserError naming the file when the bundle is damaged
            if cameras is not None:
                bundle["cameras"] = cameras
            if mesh is not None:  # (ctgs.formats.mesh.viewer_mesh)
                bundle["mesh"] = mesh[0]
            bundle_dir, bundle_json = os.path.abspath(bundle_dir), json.dumps(bundle).encode()
        handler = partial(_Handler, bundle_dir=bundle_dir, bundle_json=bundle_json, quiet=quiet,
                          mesh_bin=None if mesh is None else mesh[1], live=live)
        self.httpd = _Server((HOST, port), handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.url = f"http://{HOST}:{self.port}/"
        self._thread: threading.Thread | None = None

    def serve_forever(self) -> None:
        self.httpd.serve_forever()

    def start(self) -> "ViewerServer":
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join()
        self.httpd.server_close()

    def __enter__(self) -> "ViewerServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
