"""benchmarks/blame.py finds a planted floater: an opaque primitive in front of one test camera only."""

from __future__ import annotations

import math
import os
import sys

import pytest
import torch

from fixture_run import make_run

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks"))
import blame  # noqa: E402


def _plant_floater(run: str, view: str) -> int:
    """Add one opaque, large, grey surfel 0.3 units in front of test camera `view`, facing it; returns its index."""
    from ctgs.model.geometry import rotmat_to_quat
    from ctgs.model.surfels import jagged_offsets
    from ctgs.scene import load_scene

    path = os.path.join(run, "model.pt")
    blob = torch.load(path, weights_only=False)
    st = blob["model"]
    scene = load_scene(blob["scene_dir"], images=blob["images"], holdout=blob["holdout"], load_images=False)
    cam = next(v.camera for v in scene.test if v.name == view)
    r_c2w = cam.R.float().T  # columns: camera x, y, z (viewing axis) in world
    centre = cam.center.float() + 0.3 * r_c2w[:, 2]
    n = st["means"].shape[0]
    st["means"] = torch.cat([st["means"], centre[None]])
    st["log_scales"] = torch.cat([st["log_scales"], torch.full((1, 2), math.log(0.2))])
    st["quats"] = torch.cat([st["quats"], rotmat_to_quat(r_c2w[None])])  # surfel normal = the viewing axis
    st["opacity_logits"] = torch.cat([st["opacity_logits"], torch.tensor([6.0])])
    st["sh"] = torch.cat([st["sh"], torch.zeros(1, *st["sh"].shape[1:])])
    for key, fill in (("k_min", 0.01), ("t2p_exp", 0)):
        st[key] = torch.cat([st[key], torch.tensor([fill], dtype=st[key].dtype)])
    st["tex_res"] = torch.cat([st["tex_res"], torch.zeros(1, 2, dtype=st["tex_res"].dtype)])
    st["tex_offset"] = jagged_offsets(st["tex_res"])
    torch.save(blob, path)
    return n


def _images_from_model(run: str) -> None:
    """Replace the scene's photos by the run's own renders (8-bit): the clean model then fits every view."""
    from ctgs.io.images import write_image
    from ctgs.io.run_model import load_run
    from ctgs.render.api import render
    from ctgs.scene import load_scene

    r = load_run(run)
    scene = load_scene(r.scene_dir, images=r.images, holdout=r.holdout, load_images=False)
    with torch.no_grad():
        inputs = r.model.render_inputs()
        for v in scene.train + scene.test:
            rgb = render(inputs, v.camera, sh_degree=r.model.sh_degree).rgb.clamp(0, 1)
            write_image(v.image_path, rgb.numpy(), bits=8)


def test_blame_ranks_the_planted_floater_first(tmp_path):
    run = make_run(str(tmp_path), views=9, width=48, height=36, n=300)
    _images_from_model(run)
    planted = _plant_floater(run, "000.png")
    res = blame.blame(run, None, candidates=20)
    assert res["view"] == "000.png"  # the default is the worst view, which the floater made
    top = res["rows"][0]
    assert top["primitive"] == planted
    assert top["gain_db"] > 1.0
    assert top["dist_to_test_camera"] == pytest.approx(0.3, abs=1e-3)
    assert top["opacity"] > 0.99
    # every other candidate costs far less than the floater; removing the worst ones together gains at least as much
    assert all(r["gain_db"] < top["gain_db"] / 2 for r in res["rows"][1:])
    assert res["removed_together"]["gain_db"] >= top["gain_db"] - 0.5
    assert res["primitives"] == planted + 1
    cov = res["coverage"]
    assert 0.0 <= cov["open_fraction"] <= 1.0 and 0.0 <= cov["open_error_share"] <= 1.0

