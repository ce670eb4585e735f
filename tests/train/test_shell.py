"""The far shell of initial points (ctgs.train.components.shell, config key init_shell)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ctgs.render.camera import Camera
from ctgs.train.components.shell import SHELL_RADIUS_FACTOR, fibonacci_sphere, shell_points


def _view(colour, yaw=0.0, w=40, h=30):
    c, s = np.cos(yaw), np.sin(yaw)
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = torch.tensor([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=torch.float64)  # world -> camera
    cam = Camera(fx=30.0, fy=30.0, cx=w / 2, cy=h / 2, width=w, height=h, viewmat=vm)
    return SimpleNamespace(camera=cam, image=np.broadcast_to(np.asarray(colour, np.float32), (h, w, 3)).copy())


def test_fibonacci_sphere_is_unit_and_spread():
    d = fibonacci_sphere(500)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert abs(d.mean(0)).max() < 0.01  # no hemisphere favoured


def test_shell_points_lie_where_a_camera_looks_past_the_sfm_points_and_take_its_colour():
    rng = np.random.default_rng(0)
    # SfM points fill the left half of the (only) camera's image; the right half sees past them.
    pts = np.stack([rng.uniform(-1.0, -0.1, 400), rng.uniform(-0.7, 0.7, 400), np.full(400, 2.0)], 1)
    views = [_view((0.2, 0.4, 0.9))]
    xyz, rgb = shell_points(pts, views, 50)
    assert 0 < len(xyz) <= 50
    centre = np.median(pts, 0)
    reach = max(np.quantile(np.linalg.norm(pts - centre, axis=1), 0.98), np.linalg.norm(centre))
    assert np.allclose(np.linalg.norm(xyz - centre, axis=1), SHELL_RADIUS_FACTOR * reach, rtol=1e-6)
    cam = views[0].camera
    p = xyz @ cam.R.numpy().T + cam.t.numpy()
    u, v = cam.fx * p[:, 0] / p[:, 2] + cam.cx, cam.fy * p[:, 1] / p[:, 2] + cam.cy
    assert (p[:, 2] > 0).all() and ((u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)).all()
    q = pts @ cam.R.numpy().T + cam.t.numpy()
    sfm_u = cam.fx * q[:, 0] / q[:, 2] + cam.cx
    assert u.min() > sfm_u.max()  # none behind the SfM points (their cells, dilated, lie left of every shell point)
    assert np.allclose(rgb, [0.2, 0.4, 0.9], atol=1e-6)
    # A second camera turned away sees other directions: more of the shell, and its colour where only it looks.
    xyz2, rgb2 = shell_points(pts, views + [_view((1.0, 0.0, 0.0), yaw=np.pi)], 1000)
    assert len(xyz2) > len(xyz) and np.isclose(rgb2[:, 0], 1.0).any() and np.isclose(rgb2[:, 0], 0.2).any()


def test_no_shell_when_off():
    xyz, rgb = shell_points(np.zeros((5, 3)), [_view((0.5, 0.5, 0.5))], 0)
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3)


def test_init_shell_trains(tmp_path):
    """A short run with init_shell starts with the shell's primitives on top of the SfM ones."""
    from ctgs.runs import training_scene
    from ctgs.scene.demo import make_demo_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.loop.trainer import Trainer

    scene_dir = make_demo_scene(str(tmp_path / "demo"), num_views=8, width=96, height=72, points=40)

    def first_count(run: str, sets: list[str]) -> int:
        cfg = resolve_config(scene_dir, run, None, 1, sets + ["threads=1"], None, False, None, None, preset="fast")
        return Trainer(cfg, training_scene(cfg), run).model.num_primitives

    base = first_count(str(tmp_path / "a"), [])
    shell = first_count(str(tmp_path / "b"), ["init_shell=30"])
    assert base < shell <= base + 30


def test_far_mask_and_scene_sphere():
    from ctgs.train.components.shell import scene_sphere
    from ctgs.train.routines.far import FAR_FACTOR, far_mask

    pts = np.random.default_rng(1).normal(size=(500, 3))
    views = [_view((0.5, 0.5, 0.5))]  # camera at the origin
    centre, reach = scene_sphere(pts, views)
    assert np.allclose(centre, np.median(pts, 0))
    assert reach >= np.quantile(np.linalg.norm(pts - centre, axis=1), 0.98) - 1e-12
    means = torch.tensor(np.stack([centre, centre + [FAR_FACTOR * reach * 0.99, 0, 0],
                                   centre + [0, 0, FAR_FACTOR * reach * 1.01]]), dtype=torch.float32)
    assert far_mask(means, centre, reach).tolist() == [False, False, True]


def test_full_routine_leaves_background_primitives_out_of_split_and_upscale(monkeypatch):
    """The top fraction is taken among the non-background primitives; background ones are never split or upscaled,
    however large their error."""
    from dataclasses import replace

    from ctgs.train.config import TrainConfig
    from ctgs.train.routines import passes as routines
    from train_helpers import camera, model, optimiser

    n = 20
    xs = torch.linspace(-1.0, 1.0, n)
    m = model(means=torch.stack([xs, torch.zeros(n), torch.full((n,), 4.0)], 1), scales=[[0.3, 0.3]] * n,
              opacities=[0.9] * n, tex_res=[[8, 8]] * n, t2p_exp=[3] * n)
    opt = optimiser(m)
    bg = torch.zeros(n, dtype=torch.bool)
    bg[:5] = True  # the background holds the five largest errors
    E = torch.cat([torch.linspace(10.0, 6.0, 5), torch.linspace(5.0, 0.5, n - 5)])
    monkeypatch.setattr(routines, "compute_E", lambda *a, **k: E.clone())
    cfg = replace(TrainConfig(), top_fraction=0.2, tau_tr_start=1e9, tau_tr_end=1e9, tau_ds=-1.0,
                  prune_opacity=0.0, max_texture_res=64)
    tag = m.means.detach()[:, 0].clone()  # identifies primitives through the routine (no splits: tau_tr huge)
    exp0 = m.t2p_exp.clone()
    stats = routines.full_routine(m, opt, cfg, 1, [], None, [camera()], background=lambda mm: bg.clone())
    assert stats["split"] == 0 and m.num_primitives == n and torch.equal(m.means.detach()[:, 0], tag)
    upscaled = m.t2p_exp < exp0
    assert not upscaled[:5].any()  # background: never upscaled
    assert upscaled.nonzero().flatten().tolist() == [5, 6, 7]  # 20% of the 15 others: the top 3 by E
    # Without the mask the background takes the slots.
    m2 = model(means=torch.stack([xs, torch.zeros(n), torch.full((n,), 4.0)], 1), scales=[[0.3, 0.3]] * n,
               opacities=[0.9] * n, tex_res=[[8, 8]] * n, t2p_exp=[3] * n)
    routines.full_routine(m2, optimiser(m2), cfg, 1, [], None, [camera()])
    assert (m2.t2p_exp < 3).nonzero().flatten().tolist() == [0, 1, 2, 3]


def test_composite_is_the_single_render_where_open_and_the_background_elsewhere():
    from ctgs.render import render
    from ctgs.train.components.shell import composite
    from train_helpers import H, W, camera, model

    # Two scene surfels in front (z 3-3.5), two far ones behind (z 40) covering the whole image.
    m = model(means=[[-0.25, 0.0, 3.0], [0.3, 0.1, 3.5], [0.0, 0.0, 40.0], [3.0, 0.0, 40.0]],
              scales=[[0.2, 0.15], [0.15, 0.2], [30.0, 30.0], [30.0, 30.0]], opacities=[0.7, 0.8, 0.9, 0.6],
              tex_res=[[4, 4]] * 4)
    far = torch.tensor([False, False, True, True])
    bg = torch.tensor([0.9, 0.1, 0.4])
    inp, cam = m.render_inputs(), camera()
    fn = lambda i, c, background: render(i, c, backend="cpu", sh_degree=0, background=background)  # noqa: E731
    whole = render(inp, cam, backend="cpu", sh_degree=0, background=bg)
    rgb, ras = composite(fn, inp, cam, far, torch.ones(H, W, dtype=torch.bool), bg)
    assert torch.allclose(rgb, whole.rgb, atol=1e-5)
    assert torch.equal(ras, whole.rasterized)
    # Nowhere open: the far surfels do not show; the scene alone over the background.
    rgb0, _ = composite(fn, inp, cam, far, torch.zeros(H, W, dtype=torch.bool), bg)
    o = inp.opacities.detach().clone()
    o[far] = 0
    from dataclasses import replace
    near = render(replace(inp, opacities=o), cam, backend="cpu", sh_degree=0, background=bg)  # far ones at zero
    assert torch.allclose(rgb0, near.rgb, atol=1e-5)
    assert (rgb0 - whole.rgb).abs().max() > 0.05  # the far surfels did show in the single render
    # Gradients reach the far surfels only through open pixels.
    m.opacity_logits.grad = None
    open_left = torch.zeros(H, W, dtype=torch.bool)
    open_left[:, : W // 2] = True
    composite(fn, m.render_inputs(), cam, far, open_left, bg)[0].sum().backward()
    assert m.opacity_logits.grad[2:].abs().sum() > 0


def test_open_mask_marks_pixels_past_the_sfm_points():
    from ctgs.train.components.shell import open_mask

    rng = np.random.default_rng(0)
    pts = np.stack([rng.uniform(-1.0, -0.1, 400), rng.uniform(-0.7, 0.7, 400), np.full(400, 2.0)], 1)
    cam = _view((0.5, 0.5, 0.5)).camera
    mask = open_mask(pts, cam)
    assert mask.shape == (cam.height, cam.width)
    assert not mask[:, : cam.width // 2 - 2].any() and mask[:, -4:].all()


@pytest.mark.slow
def test_a_short_run_with_a_shell_composites_its_training_renders_and_never_splits_far_primitives(tmp_path, monkeypatch):
    """Through whole routines: every training render goes through shell.composite, and no split reaches a far
    (shell) primitive, so their number never grows in a routine (upscales: the unit test above)."""
    from ctgs.runs import training_scene
    from ctgs.scene.demo import make_demo_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train import components
    from ctgs.train.components import shell
    from ctgs.train.loop.trainer import Trainer
    from ctgs.train.routines import passes as routines
    from ctgs.train.strategies import content_aware

    scene_dir = make_demo_scene(str(tmp_path / "demo"), num_views=8, width=96, height=72, points=300)
    cfg = resolve_config(scene_dir, str(tmp_path / "run"), None, 200, ["init_shell=40", "threads=1"], None, False,
                         None, None, preset="fast")
    calls = {"composite": 0}

    real = shell.composite

    def counted(*a, **k):
        calls["composite"] += 1
        return real(*a, **k)

    monkeypatch.setattr(shell, "composite", counted)
    seen = []
    real_full = routines.full_routine

    def watched(model, opt, cfg_, it, views, render_fn, cameras, background=None, **kw):
        before = int(background(model).sum())
        stats = real_full(model, opt, cfg_, it, views, render_fn, cameras, background, **kw)
        seen.append((before, int(background(model).sum()), stats))
        return stats

    monkeypatch.setattr(content_aware, "full_routine", watched)
    t = Trainer(cfg, training_scene(cfg), str(tmp_path / "run"))
    t.time.estimator = None  # its calibration renders a copy (covered below, with --time-budget); count the run's only
    far0 = int(shell.far_mask(t.model.means, *t.part(components.Shell).sphere).sum())
    assert far0 > 0
    for _ in t.run():
        pass
    assert calls["composite"] == 200
    assert seen and any(s[2]["split"] + s[2]["upscaled"] > 0 for s in seen)  # the routines did refine the scene
    for n_far, n_after, _ in seen:
        assert n_after <= n_far  # no far children (primitives drift, but none is split off out there)


def test_time_budget_calibration_times_the_training_render_with_a_shell(tmp_path, monkeypatch):
    """With init_shell a training step renders twice (shell.composite); --time-budget's calibration must time that
    step, not a single render, or the plan undercounts every step."""
    from ctgs.runs import training_scene
    from ctgs.scene.demo import make_demo_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.components import shell
    from ctgs.train.loop.calibration import calibrate
    from ctgs.train.loop.trainer import Trainer

    scene_dir = make_demo_scene(str(tmp_path / "demo"), num_views=6, width=64, height=48, points=200)
    calls = {"composite": 0}

    real = shell.composite

    def counted(*a, **k):
        calls["composite"] += 1
        return real(*a, **k)

    monkeypatch.setattr(shell, "composite", counted)
    for sets, expected in ((["init_shell=20", "threads=1"], 6), (["threads=1"], 0)):
        calls["composite"] = 0
        cfg = resolve_config(scene_dir, str(tmp_path / f"run{expected}"), None, 50, sets, None, False, None, None,
                             preset="fast")
        t = Trainer(cfg, training_scene(cfg), str(tmp_path / f"run{expected}"))
        step_s, render_s, textured_s, _ = calibrate(t)
        assert step_s > 0 and render_s > 0 and textured_s > 0
        # three timed steps before and three after the texture start, each through composite with a shell
        assert calls["composite"] == expected
