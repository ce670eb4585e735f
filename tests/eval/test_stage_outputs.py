"""`ctgs render` and `ctgs eval` outputs: render succeeds and matches eval's renders; a failure part-way
leaves no folder (and an earlier one intact); -o never replaces a folder that is not an earlier output."""

from __future__ import annotations

import os

import pytest
from click.testing import CliRunner

import ctgs.io.images
from fixture_run import make_run
from ctgs.cli import STAGES, main
from ctgs.io.owner import MARKER


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return make_run(str(tmp_path_factory.mktemp("outputs")))


def _invoke(*args):
    return CliRunner().invoke(main, list(args))


def _fail_on_write(monkeypatch, after: int):
    """write_image raises on call number after + 1 (the earlier calls write normally)."""
    real, calls = ctgs.io.images.write_image, []

    def flaky(path, *a, **k):
        calls.append(path)
        if len(calls) > after:
            raise OSError(f"{path}: disk full (injected)")
        return real(path, *a, **k)

    monkeypatch.setattr(ctgs.io.images, "write_image", flaky)
    return calls


def test_render_writes_the_test_views_like_eval(run_dir, tmp_path):
    res = _invoke("render", run_dir, "-o", str(tmp_path / "r"), "--backend", "reference")
    assert res.exit_code == 0, res.output
    # 9 views, every 8th is a test view; the marker that makes the folder render's to replace later
    assert sorted(os.listdir(tmp_path / "r")) == [MARKER, "000.png", "008.png"]
    res = _invoke("eval", run_dir, "-o", str(tmp_path / "e"), "--backend", "reference", "--no-lpips")
    assert res.exit_code == 0, res.output
    for name in ("000.png", "008.png"):  # same model, cameras and backend: the same 8-bit images
        assert (tmp_path / "r" / name).read_bytes() == (tmp_path / "e" / "renders" / name).read_bytes()
    img = ctgs.io.images.read_image(str(tmp_path / "r" / "000.png"))
    assert img.shape == (32, 40, 3) and img.std() > 0.01  # drawn, not a blank frame
    res = _invoke("render", run_dir, "-o", str(tmp_path / "r"), "--views", "all", "--backend", "reference")
    assert res.exit_code == 0 and len(os.listdir(tmp_path / "r")) == 9 + 1  # an earlier render folder is replaced


def test_render_maps_normal_and_depth(run_dir, tmp_path):
    """--maps rgb,normal,depth: the colour PNG as without it; a 16-bit RGBA normal map ((n + 1) / 2, unit normals
    facing the camera where drawn, alpha as in a colour render); a float32 EXR of depth / alpha."""
    import numpy as np
    import torch

    from ctgs.runs import load_run
    from ctgs.render import render
    from ctgs.scene.loader import load_scene

    res = _invoke("render", run_dir, "-o", str(tmp_path / "m"), "--backend", "cpu", "--maps", "rgb,normal,depth")
    assert res.exit_code == 0, res.output
    assert sorted(os.listdir(tmp_path / "m")) == [MARKER, "000.depth.exr", "000.normal.png", "000.png", "008.depth.exr",
                                                  "008.normal.png", "008.png"]
    assert _invoke("render", run_dir, "-o", str(tmp_path / "c"), "--backend", "cpu").exit_code == 0
    assert (tmp_path / "m" / "000.png").read_bytes() == (tmp_path / "c" / "000.png").read_bytes()
    run = load_run(run_dir)
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout, load_images=False)
    with torch.no_grad():
        out = render(run.model.render_inputs(), scene.test[0].camera, backend="cpu", sh_degree=run.model.sh_degree)
    nmap = ctgs.io.images.read_image(str(tmp_path / "m" / "000.normal.png"))
    assert nmap.shape == (32, 40, 4)
    assert np.allclose(nmap[..., 3], out.alpha.numpy(), atol=1e-4)  # 16-bit alpha
    drawn = out.alpha.numpy() > 0.5
    n = nmap[..., :3] * 2 - 1
    assert drawn.sum() > 100
    assert np.allclose(np.linalg.norm(n[drawn], axis=-1), 1.0, atol=2e-3)
    cam = scene.test[0].camera  # facing the camera: n . ray <= 0 along every pixel's ray (a surfel's plane holds
    u = (np.arange(40) + 0.5 - cam.cx) / cam.fx  # its hit points, all on one side of the camera centre)
    v = (np.arange(32) + 0.5 - cam.cy) / cam.fy
    ray = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((32, 40))), -1)
    assert ((n * ray).sum(-1)[drawn] <= 2e-3).all()
    depth = ctgs.io.images.read_image(str(tmp_path / "m" / "000.depth.exr"))
    assert depth.dtype == np.float32 and depth.shape[:2] == (32, 40)
    want = (out.depth / out.alpha.clamp_min(1e-6)).numpy()
    assert np.allclose(depth.reshape(32, 40)[drawn], want[drawn], rtol=1e-6)
    res = _invoke("render", run_dir, "-o", str(tmp_path / "x"), "--maps", "rgb,albedo")
    assert res.exit_code == 2 and "--maps" in res.output and not (tmp_path / "x").exists()


@pytest.mark.parametrize("after", [0, 1])
def test_render_failure_leaves_no_folder(run_dir, tmp_path, monkeypatch, after):
    calls = _fail_on_write(monkeypatch, after)
    res = _invoke("render", run_dir, "-o", str(tmp_path / "r"), "--backend", "reference")
    assert res.exit_code != 0 and len(calls) == after + 1
    assert os.listdir(tmp_path) == []  # neither the folder nor a temporary sibling


@pytest.mark.parametrize("after", [0, 2, 3])  # first render, first strip, last strip (2 renders, 2 strips)
def test_eval_failure_leaves_no_folder_and_keeps_an_earlier_one(run_dir, tmp_path, monkeypatch, after):
    out = tmp_path / "e"
    assert _invoke("eval", run_dir, "-o", str(out), "--backend", "reference", "--no-lpips").exit_code == 0
    before = (out / "metrics.json").read_bytes()
    calls = _fail_on_write(monkeypatch, after)
    res = _invoke("eval", run_dir, "-o", str(out), "--backend", "reference", "--no-lpips", "--dataset", "other")
    assert res.exit_code != 0 and len(calls) == after + 1
    assert os.listdir(tmp_path) == ["e"] and (out / "metrics.json").read_bytes() == before
    res = _invoke("eval", run_dir, "-o", str(tmp_path / "fresh"), "--backend", "reference", "--no-lpips")
    assert res.exit_code != 0 and not (tmp_path / "fresh").exists()


@pytest.mark.parametrize("stage", ["eval", "render"])
def test_output_that_is_not_an_earlier_output_is_refused(run_dir, tmp_path, stage):
    # -o pointing at the run folder itself must not replace (delete) it.
    before = sorted(os.listdir(run_dir))
    res = _invoke(stage, run_dir, "-o", run_dir, "--backend", "reference", *(["--no-lpips"] if stage == "eval" else []))
    assert res.exit_code == 2 and f"not an earlier `ctgs {stage}` folder" in res.output
    assert sorted(os.listdir(run_dir)) == before


def test_every_stage_spells_the_output_option_the_same():
    from click import Context

    for name in STAGES:
        cmd = main.get_command(Context(main), name)
        for param in cmd.params:
            if "-o" in param.opts or any(o.startswith("--out") for o in param.opts):
                assert param.opts == ["-o", "--output"], (name, param.opts)
