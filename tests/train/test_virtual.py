"""Virtual-view coverage (ctgs.train.components.virtual, config keys virtual_coverage / virtual_every)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ctgs.render.camera import Camera
from ctgs.train.components.virtual import coverage_loss, virtual_views

W, H, F = 40, 30, 40.0


def cam_at(x: float) -> Camera:
    """Camera centred at (x, 0, 0) looking down +z."""
    vm = torch.eye(4, dtype=torch.float64)
    vm[0, 3] = -x
    return Camera(fx=F, fy=F, cx=W / 2, cy=H / 2, width=W, height=H, viewmat=vm)


def wall() -> np.ndarray:
    rng = np.random.default_rng(0)
    z = rng.uniform(4.0, 6.0, 400)
    return np.stack([rng.uniform(-0.4, 0.4, 400) * z, rng.uniform(-0.3, 0.3, 400) * z, z], 1)


def test_two_virtual_views_per_camera_half_a_step_each_way():
    cams = [cam_at(0.0), cam_at(0.2), cam_at(1.0)]
    vv = virtual_views(["a", "b", "c"], cams, wall())
    centres = {v.name: float(v.camera.center[0]) for v in vv}
    # a's nearest is b (0.2 away), b's is a, c's is b (0.8 away)
    assert centres == pytest.approx({"a+": 0.1, "a-": -0.1, "b+": 0.1, "b-": 0.3, "c+": 0.6, "c-": 1.4})
    for v in vv:
        assert v.camera.width == W and v.camera.height == H and torch.equal(v.camera.R, cams[0].R)
        assert v.mask.shape == (H, W) and v.held == int(v.mask.sum()) > 0
    # c- (0.4 right of the rightmost camera) sees past the training images on its right at near depths
    c_minus = next(v for v in vv if v.name == "c-")
    assert c_minus.mask[:, -1].sum() == 0 and c_minus.mask[:, 0].all()
    a_plus = next(v for v in vv if v.name == "a+")
    assert a_plus.mask.all()  # between two training cameras: held everywhere


def test_few_pixels_are_the_held_ones_only_one_or_two_cameras_see():
    """Four cameras in a row: the few pixels are a subset of the held ones, and half a step beyond either end of the
    row they lie on the outer side (the columns fewer cameras see)."""
    cams = [cam_at(x) for x in (0.0, 0.2, 0.4, 0.6)]
    held = {v.name: v for v in virtual_views(list("abcd"), cams, wall())}
    few = {v.name: v for v in virtual_views(list("abcd"), cams, wall(), pixels="few")}
    assert set(few) < set(held)
    for name, v in few.items():
        assert bool((v.mask <= held[name].mask).all()) and 0 < v.held < held[name].held
        assert v.norm == H * W and held[name].norm == held[name].held  # few: per-pixel weight 1 / (H W)
    left, right = few["a-"].mask[:, : W // 2].sum(), few["a-"].mask[:, W // 2:].sum()  # a- is left of the row
    assert left > right
    left, right = few["d-"].mask[:, : W // 2].sum(), few["d-"].mask[:, W // 2:].sum()  # d- is right of it
    assert right > left
    with pytest.raises(ValueError, match="pixels"):
        virtual_views(list("abcd"), cams, wall(), pixels="all")


def test_no_virtual_views_from_one_camera_or_without_points_in_view():
    assert virtual_views(["a"], [cam_at(0.0)], wall()) == []
    behind = wall() * np.array([1, 1, -1])
    assert virtual_views(["a", "b"], [cam_at(0.0), cam_at(0.2)], behind) == []


def test_coverage_loss_counts_only_held_pixels_and_pulls_alpha_up():
    cams = [cam_at(0.0), cam_at(0.2)]
    v = virtual_views(["a", "b"], cams, wall())[0]
    v.mask[:, : W // 2] = 0  # only the right half held
    v.held = v.norm = int(v.mask.sum())
    alpha = torch.full((H, W), 0.25, requires_grad=True)
    with torch.no_grad():
        alpha[:, : W // 2] = 0.0  # open where not held: costs nothing
    loss = coverage_loss(alpha, v)
    assert float(loss.detach()) == pytest.approx(0.75)
    loss.backward()
    assert (alpha.grad[:, W // 2:] < 0).all() and (alpha.grad[:, : W // 2] == 0).all()


def test_virtual_coverage_trains_and_raises_alpha_between_cameras(tmp_path):
    """A short run with the term trains, and leaves the virtual views less open than the same run without it."""
    from ctgs.render import render
    from ctgs.runs import training_scene
    from ctgs.scene.demo import make_demo_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.components import VirtualCoverage
    from ctgs.train.loop.trainer import Trainer

    scene_dir = make_demo_scene(str(tmp_path / "demo"), num_views=8, width=64, height=48, points=300)

    def train(run: str, sets: list[str]) -> Trainer:
        cfg = resolve_config(scene_dir, run, None, 60, sets + ["threads=1", "seed=3"], None, False, None, None,
                             preset="fast")
        t = Trainer(cfg, training_scene(cfg), run)
        for _ in t.run():
            pass
        return t

    on = train(str(tmp_path / "on"), ["virtual_coverage=1.0", "virtual_every=1"])
    off = train(str(tmp_path / "off"), [])
    assert len(on.part(VirtualCoverage).views) > 0 and off.part(VirtualCoverage) is None

    def mean_alpha(t: Trainer) -> float:
        with torch.no_grad():
            inp = t.model.render_inputs()
            return float(np.mean([float(coverage_loss(render(inp, v.camera, sh_degree=t.model.sh_degree).alpha, v))
                                  for v in on.part(VirtualCoverage).views]))

    assert mean_alpha(on) < 0.8 * mean_alpha(off)  # (1 - alpha) on the virtual views: 0.04-0.14 vs 0.13-0.24


def test_virtual_coverage_rejects_a_negative_weight_a_zero_cadence_and_an_unknown_pixel_kind():
    from ctgs.errors import UserError
    from ctgs.train.config import load_config

    for key, value in (("virtual_coverage", -1.0), ("virtual_every", 0), ("virtual_pixels", "all")):
        with pytest.raises(UserError, match=key):
            load_config(None, {key: value})
