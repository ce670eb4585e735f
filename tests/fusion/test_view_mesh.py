"""`ctgs view --mesh`: the server hands the mesh to the page, and the page draws it where the camera puts it (headless
Chromium, software WebGL2: a known quad against its projection, pixel for pixel), toggled with M."""

from __future__ import annotations

import json
import os
import sys
import urllib.error
import urllib.request

import numpy as np
import pytest
from surface_model import demo_scene, surface_model

from ctgs.formats.mesh import viewer_mesh, write_mesh
from ctgs.formats.web_bundle import scene_cameras, write_web_bundle
from ctgs.viewer.server import ViewerServer

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "benchmarks"))  # the headless-browser libraries of the benchmarks
from headless import Browser, BrowserError, find_chromium  # noqa: E402
from viewer_page import ViewerPage  # noqa: E402

CAMERA = 3
NO_CHROMIUM = "no Chromium to drive (Debian: apt-get install -y chromium, which .ci/run does; or set CTGS_CHROMIUM)"
# The quad in camera space: x and y bounds at depth Z (camera units), red.
X0, X1, Y0, Y1, Z = -0.35, 0.25, -0.2, 0.3, 1.5


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> dict:
    root = str(tmp_path_factory.mktemp("view_mesh"))
    scene = demo_scene(root)
    cams = scene_cameras(scene)
    web = os.path.join(root, "web")
    write_web_bundle(surface_model(spacing=0.12), web, cams)
    cam = cams[CAMERA]
    vm = np.asarray(cam["viewmat"], np.float64).reshape(4, 4)
    corners = np.array([[X0, Y0, Z], [X1, Y0, Z], [X1, Y1, Z], [X0, Y1, Z]])
    world = (corners - vm[:3, 3]) @ vm[:3, :3]  # camera -> world
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    colours = np.tile([1.0, 0.0, 0.0], (4, 1))
    return {"web": web, "camera": cam, "mesh": viewer_mesh(world, faces, colours), "arrays": (world, faces, colours),
            "root": root}


def _get(url: str) -> tuple[int, bytes, dict]:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status, r.read(), dict(r.headers)
    except urllib.error.HTTPError as exc:
        return exc.code, b"", dict(exc.headers)


def test_the_server_hands_over_the_mesh_and_nothing_without_one(bundle):
    info, data = bundle["mesh"]
    with ViewerServer(bundle["web"], mesh=bundle["mesh"]) as server:
        status, body, _ = _get(server.url + "bundle/bundle.json")
        assert status == 200 and json.loads(body)["mesh"] == info
        status, body, headers = _get(server.url + "bundle/mesh.bin")
        assert status == 200 and body == data and "default-src 'self'" in headers["Content-Security-Policy"]
    with ViewerServer(bundle["web"]) as server:
        assert "mesh" not in json.loads(_get(server.url + "bundle/bundle.json")[1])
        assert _get(server.url + "bundle/mesh.bin")[0] == 404


def test_view_reads_the_mesh_file_before_serving(bundle, tmp_path):
    """A damaged mesh file: one line naming it, before any server starts."""
    from click.testing import CliRunner

    from ctgs.cli import main

    bad = str(tmp_path / "bad.ply")
    open(bad, "wb").write(b"ply\nformat ascii 1.0\nend_header\n")
    res = CliRunner().invoke(main, ["view", bundle["web"], "--mesh", bad, "--no-browser", "--port", "0"])
    assert res.exit_code == 2 and res.output.strip().splitlines()[-1].startswith(f"error: {bad}: not a mesh")


@pytest.fixture(scope="module")
def page(bundle):
    if find_chromium() is None:
        pytest.skip(NO_CHROMIUM)
    with ViewerServer(bundle["web"], mesh=bundle["mesh"]) as server, Browser() as browser:
        yield ViewerPage(browser, server.url)


def test_the_mesh_is_drawn_where_the_camera_puts_it(bundle, page):
    cam = bundle["camera"]
    img = page.capture(CAMERA, mesh=True, shade=False)
    h, w = img.shape[:2]
    assert (w, h) == (cam["width"], cam["height"])
    u = (np.arange(w) + 0.5 - cam["cx"]) / cam["fx"] * Z  # camera-space x of each pixel centre at depth Z
    v = (np.arange(h) + 0.5 - cam["cy"]) / cam["fy"] * Z
    inside = ((u[None] > X0) & (u[None] < X1) & (v[:, None] > Y0) & (v[:, None] < Y1))
    # pixel centres within half a pixel of the quad's edge may go either way
    margin_u, margin_v = 0.5 * Z / cam["fx"], 0.5 * Z / cam["fy"]
    sure_in = ((u[None] > X0 + margin_u) & (u[None] < X1 - margin_u) & (v[:, None] > Y0 + margin_v)
               & (v[:, None] < Y1 - margin_v))
    sure_out = ~((u[None] > X0 - margin_u) & (u[None] < X1 + margin_u) & (v[:, None] > Y0 - margin_v)
                 & (v[:, None] < Y1 + margin_v))
    red = np.all(np.abs(img - [1.0, 0.0, 0.0]) < 1.5 / 255, axis=-1)
    background = np.all(img < 1.5 / 255, axis=-1)  # the demo's black background
    assert inside.sum() > 200 and red[sure_in].all() and background[sure_out].all()
    # shaded: a quad facing the camera keeps most of its red, and nothing else changes
    shaded = page.capture(CAMERA, mesh=True)
    assert (shaded[sure_in, 0] > 0.7).all() and (shaded[sure_in, 1:] < 1.5 / 255).all()
    assert np.all(shaded[sure_out] < 1.5 / 255)
    # the surfels: another picture altogether
    surfels = page.capture(CAMERA)
    assert np.abs(surfels - img).mean() > 0.05


def test_m_toggles_the_mesh_and_the_page_says_it_has_one(page):
    browser = page.browser
    assert page.info["meshTriangles"] == 2
    before = browser.evaluate("window.viewer.showMesh")
    browser.press("m")
    assert browser.evaluate("window.viewer.showMesh") is (not before)
    assert browser.evaluate("document.getElementById('mesh').checked") is (not before)
    assert browser.evaluate("document.getElementById('mesh-section').hidden") is False
    assert "mesh 2 triangles" in browser.evaluate("document.getElementById('stats').textContent")
    assert browser.page_errors() == []


def test_without_a_mesh_the_toggle_is_hidden(bundle):
    if find_chromium() is None:
        pytest.skip(NO_CHROMIUM)
    with ViewerServer(bundle["web"]) as server, Browser() as browser:
        page = ViewerPage(browser, server.url)
        assert page.info["meshTriangles"] == 0
        assert browser.evaluate("document.getElementById('mesh-section').hidden") is True
        with pytest.raises(BrowserError, match="no mesh to show"):
            page.capture(CAMERA, mesh=True)


def test_a_mesh_file_goes_to_the_viewer_unchanged(bundle, tmp_path):
    """What `ctgs view --mesh FILE` serves is the file's mesh (PLY here) in the viewer's arrays."""
    from ctgs.formats.mesh import read_mesh

    world, faces, colours = bundle["arrays"]
    path = str(tmp_path / "quad.ply")
    write_mesh(path, world, faces, colours)
    info, data = viewer_mesh(*read_mesh(path))
    assert info == bundle["mesh"][0] and data == bundle["mesh"][1]
