"""`ctgs view` and its server: static files from the package, the bundle, cameras override, errors;
the shaders' constants equal the renderer's."""

from __future__ import annotations

import json
import os
import re
import socket
import urllib.error
import urllib.request

import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.formats.model_format import write_model
from ctgs.formats.web_bundle import write_web_bundle
from ctgs.render import constants
from ctgs.stages.view import resolve_bundle
from ctgs.viewer.server import STATIC_DIR, ViewerServer
from viewer_models import textured_model

STATIC_FILES = ("index.html", "viewer.css", "viewer.js", "renderer.js", "camera.js", "bundle.js",
                "sort_worker.js", "surfel.vert", "surfel.frag", "composite.vert", "composite.frag", "camera_path.js",
                "live.js")


def _get(url: str) -> tuple[int, bytes, str]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read(), r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as exc:
        return exc.code, b"", ""


@pytest.fixture
def bundle_dir(tmp_path) -> str:
    cams = [{"name": "x.png", "split": "train", "width": 8, "height": 6, "fx": 8.0, "fy": 8.0, "cx": 4.0,
             "cy": 3.0, "near": 0.01, "viewmat": [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 3, 0, 0, 0, 1]}]
    write_web_bundle(textured_model(n=12), str(tmp_path / "web"), cams)
    return str(tmp_path / "web")


def test_every_asset_is_local_and_served(bundle_dir):
    with ViewerServer(bundle_dir) as srv:
        assert srv.url.startswith("http://127.0.0.1:")
        for name in STATIC_FILES:
            status, body, ctype = _get(srv.url + name)
            assert status == 200 and body, name
            if name.endswith(".js"):
                assert ctype.startswith("text/javascript"), (name, ctype)  # module scripts need it
        status, body, _ = _get(srv.url)
        assert status == 200 and b"viewer.js" in body
        bundle = json.loads(_get(srv.url + "bundle/bundle.json")[1])
        assert bundle["num_surfels"] == 12 and bundle["cameras"][0]["name"] == "x.png"
        assert _get(srv.url + "bundle/surfels.bin")[0] == 200
        # only the bundle's own flat files: nothing above or beside it
        assert _get(srv.url + "bundle/%2e%2e/web/bundle.json")[0] == 404
        assert _get(srv.url + "bundle/..%2fweb%2fbundle.json")[0] == 404
    # nothing may come from the internet: no absolute URLs in the page or its scripts
    for name in STATIC_FILES:
        text = open(os.path.join(STATIC_DIR, name)).read()
        assert not re.search(r"(src|href)\s*=\s*[\"']?(https?:)?//", text), name
        assert not re.search(r"(import|fetch)\s*\(?\s*[\"']https?://", text), name


def test_cameras_override(bundle_dir):
    cams = [{"name": "other.png", "split": "test", "width": 4, "height": 4, "fx": 4.0, "fy": 4.0, "cx": 2.0,
             "cy": 2.0, "near": 0.01, "viewmat": [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 3, 0, 0, 0, 1]}]
    with ViewerServer(bundle_dir, cameras=cams) as srv:
        assert json.loads(_get(srv.url + "bundle/bundle.json")[1])["cameras"] == cams


def test_shader_constants_equal_the_renderer_constants():
    expected = {"MAX_ALPHA": constants.MAX_ALPHA, "MIN_ALPHA": constants.MIN_ALPHA,
                "CUTOFF_RHO": constants.CUTOFF_RHO, "FILTER_INV_SQUARE": constants.FILTER_INV_SQUARE,
                "PARALLEL_EPS": constants.PARALLEL_EPS}
    seen = {}
    for name in ("surfel.vert", "surfel.frag"):
        for key, value in re.findall(r"^#define (\w+) (.+?)(?:\s*//.*)?$", open(os.path.join(STATIC_DIR, name)).read(),
                                     flags=re.M):
            if key in expected:
                seen[key] = eval(value.replace("(", "").replace(")", ""), {})  # numeric literals only
                assert seen[key] == pytest.approx(expected[key], rel=1e-12), (name, key)
    assert set(seen) == set(expected)


def test_the_texel_map_scales_and_colours_of_the_shaders_are_the_renderers():
    from ctgs.render import texel_map

    expected = {"TEXEL_PX_LOG2_LO": texel_map.TEXEL_PX_LOG2[0], "TEXEL_PX_LOG2_HI": texel_map.TEXEL_PX_LOG2[1],
                "TEXRES_LOG2_LO": texel_map.TEXRES_LOG2[0], "TEXRES_LOG2_HI": texel_map.TEXRES_LOG2[1],
                "UNTEXTURED": texel_map.UNTEXTURED, "MIN_WEIGHT": texel_map.MIN_WEIGHT}
    seen = {}
    for name in ("surfel.vert", "composite.frag"):
        for key, value in re.findall(r"^#define (\w+) (\S+)", open(os.path.join(STATIC_DIR, name)).read(), flags=re.M):
            if key in expected:
                seen[key] = float(value)
                assert seen[key] == expected[key], (name, key)
    assert set(seen) == set(expected)
    frag = open(os.path.join(STATIC_DIR, "composite.frag")).read()
    table = re.search(r"TURBO\[(\d+)\] = vec3\[\d+\]\((.*?)\);", frag, flags=re.S)
    rows = [[float(v) for v in row.split(",")] for row in re.findall(r"vec3\(([^)]*)\)", table.group(2))]
    assert int(table.group(1)) == len(texel_map.TURBO) and rows == texel_map.TURBO.astype(float).round(3).tolist()
    legend = open(os.path.join(STATIC_DIR, "live.js")).read()  # the legend's gradient: the same table
    js = re.search(r"const TURBO = \[(.*?)\];", legend, flags=re.S).group(1)
    assert [[float(v) for v in row.split(",")] for row in re.findall(r"\[([^\[\]]*)\]", js)] == rows


def test_resolve_bundle_builds_one_for_a_plain_model_folder(tmp_path):
    model_dir = str(tmp_path / "model")
    write_model(textured_model(n=9), model_dir, plain_ply=False)
    bundle_dir, cameras, how = resolve_bundle(model_dir, None, str(tmp_path / "tmp"))
    assert how == "built from the model folder" and cameras is None
    assert json.load(open(os.path.join(bundle_dir, "bundle.json")))["num_surfels"] == 9
    assert sorted(os.listdir(model_dir)) == [".ctgs-output", "manifest.json", "primitives.ply", "textures.bin"]  # untouched


def test_view_user_errors_are_one_line(tmp_path):
    result = CliRunner().invoke(main, ["view", str(tmp_path / "nope"), "--no-browser"])
    assert result.exit_code == 2 and "model folder not found" in result.output
    assert len(result.output.strip().splitlines()) == 1
    (tmp_path / "empty").mkdir()
    result = CliRunner().invoke(main, ["view", str(tmp_path / "empty"), "--no-browser"])
    assert result.exit_code == 2 and "neither a model folder nor a web bundle" in result.output


def test_view_port_in_use_is_a_user_error(bundle_dir):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        result = CliRunner().invoke(main, ["view", bundle_dir, "--no-browser", "--port", str(port)])
    assert result.exit_code == 2 and "cannot listen" in result.output and "--port" in result.output


def test_export_format_web_writes_model_and_bundle_with_the_scene_cameras(tmp_path):
    import torch

    from ctgs.scene.demo import make_demo_scene

    scene = make_demo_scene(str(tmp_path / "scene"), num_views=9, width=40, height=32, points=200, supersample=1)
    run = tmp_path / "run"
    run.mkdir()
    model = textured_model(n=15)
    torch.save({"model": model.state_dict(), "scene_dir": scene, "images": "images", "holdout": 8,
                "iteration": 1, "config": {}}, str(run / "model.pt"))
    result = CliRunner().invoke(main, ["export", str(run), "--format", "web", "--texel-bits", "16"])
    assert result.exit_code == 0, result.output
    bundle = json.load(open(run / "model" / "web" / "bundle.json"))
    assert (run / "model" / "manifest.json").is_file()
    assert bundle["num_surfels"] == 15 and bundle["atlas"]["texel_format"] == "float16"
    assert [c["split"] for c in bundle["cameras"]].count("test") == 2 and len(bundle["cameras"]) == 9
    assert {(c["width"], c["height"]) for c in bundle["cameras"]} == {(40, 32)}
    result = CliRunner().invoke(main, ["export", str(run), "-o", str(tmp_path / "plain")])
    assert result.exit_code == 0 and not (tmp_path / "plain" / "web").exists()


def _raw_get(port: int, path: str, host: str | None = None) -> int:
    import http.client

    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.putrequest("GET", path, skip_host=True, skip_accept_encoding=True)
    conn.putheader("Host", f"127.0.0.1:{port}" if host is None else host)
    conn.endheaders()
    status = conn.getresponse().status
    conn.close()
    return status


def test_malformed_paths_get_400_and_other_hosts_are_refused(bundle_dir, capfd):
    with ViewerServer(bundle_dir) as srv:
        for path in ("/bundle/%00", "/%00", "/bundle/%ff", "/bundle/a%0ab", "/bundle%5c..%5cx"):
            assert _raw_get(srv.port, path) == 400, path
        assert _raw_get(srv.port, "/bundle/bundle.json") == 200
        assert _raw_get(srv.port, "/", host=f"localhost:{srv.port}") == 200
        # DNS rebinding: a page on evil.example resolving to 127.0.0.1 sends its own name as the Host
        for host in (f"evil.example:{srv.port}", "127.0.0.1", f"127.0.0.1:{srv.port + 1}", ""):
            assert _raw_get(srv.port, "/bundle/bundle.json", host=host) == 421, host
    assert "Traceback" not in capfd.readouterr().err  # nothing printed in the user's terminal


def test_bundle_is_readable_by_others_like_every_output(tmp_path):
    # The bundle folder and its files get the modes of every other output (0755 / 0644), not mkdtemp's 0700,
    # also when an earlier bundle is replaced.
    out = str(tmp_path / "web")
    for _ in range(2):
        write_web_bundle(textured_model(n=12), out, [])
        assert os.stat(out).st_mode & 0o777 == 0o755
        for name in os.listdir(out):
            assert os.stat(os.path.join(out, name)).st_mode & 0o777 == 0o644, name
        assert sorted(os.listdir(tmp_path)) == ["web"]  # no temporary left beside it


def test_every_response_carries_the_content_security_policy(bundle_dir):
    with ViewerServer(bundle_dir) as srv:
        for path in ("", "viewer.js", "bundle/bundle.json", "bundle/surfels.bin"):
            with urllib.request.urlopen(srv.url + path, timeout=10) as r:
                csp = r.headers.get("Content-Security-Policy", "")
                assert "script-src 'self'" in csp and "frame-ancestors 'none'" in csp, (path, csp)
                assert r.headers.get("X-Content-Type-Options") == "nosniff"
