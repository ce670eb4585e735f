"""What hundreds of training views need: the opacity regulariser on rasterized primitives only, E from a sample of
the views, and an initial farthest-point subsample that does not take minutes."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import torch

from ctgs.train.config import TrainConfig, load_config
from ctgs.train.config.rules import resolve
from ctgs.train.routines.passes import error_views
from ctgs.train.start.init import farthest_point_subsample
from ctgs.train.step.adam import SurfelAdam
from ctgs.train.step.loss import training_loss

from train_helpers import H, W, camera, model


def _brute_force_fps(points: np.ndarray, k: int, seed: int) -> np.ndarray:
    """The definition: every pick updates every point's distance to the chosen set."""
    p = np.asarray(points, dtype=np.float32)
    chosen = [int(np.random.default_rng(seed).integers(len(p)))]
    dist = ((p - p[chosen[0]]) ** 2).sum(1)
    for _ in range(1, k):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, ((p - p[chosen[-1]]) ** 2).sum(1))
    return np.array(chosen)


def test_farthest_point_subsample_is_the_exact_greedy_order():
    rng = np.random.default_rng(4)
    # clustered and spread points alike (SfM points are both)
    pts = np.concatenate([rng.normal(size=(1500, 3)) * 0.01, rng.uniform(-5, 5, size=(1500, 3))])
    for k, seed in ((1, 0), (50, 1), (700, 2)):
        assert np.array_equal(farthest_point_subsample(pts, k, seed), _brute_force_fps(pts, k, seed))
    assert np.array_equal(farthest_point_subsample(pts[:10], 20), np.arange(10))


def _two_surfels():
    """One surfel in front of the camera, one behind it (never rasterized)."""
    return model([[0.0, 0.0, 3.0], [0.0, 0.0, -3.0]], [[0.3, 0.3], [0.3, 0.3]], [0.5, 0.5], [[2, 2], [2, 2]])


def _opacity_grad(cfg):
    m = _two_surfels()
    from ctgs.render import render

    out = render(m.render_inputs(), camera(), backend="cpu", sh_degree=0)
    gt = torch.full((H, W, 3), 0.5)
    training_loss(out.rgb, gt, m, camera(), cfg, rasterized=out.rasterized).total.backward()
    return m, m.opacity_logits.grad.clone()


def test_opacity_regulariser_leaves_unseen_primitives_alone_under_adam():
    cfg = replace(TrainConfig(), lambda_texture=0.0)
    assert cfg.opacity_reg_visible  # the default, as in the authors' code
    _, g_all = _opacity_grad(replace(cfg, opacity_reg_visible=False))
    assert g_all[1] > 0  # the mean over all: a gradient on the surfel no view shows ...
    m, g_vis = _opacity_grad(cfg)
    assert g_vis[1] == 0 and torch.isclose(g_vis[0], g_all[0])  # ... and none with the visible form
    # ... which under Adam is a full learning-rate step per iteration, whatever the gradient's size:
    opt = SurfelAdam(m, 1e-15)
    before = m.opacity_logits.detach().clone()
    m.opacity_logits.grad = g_all.clone()
    lrs = {name: 0.0 for name in opt.exp_avg}
    lrs["opacity_logits"] = 0.05
    opt.step(m, lrs)
    assert abs(float(before[1] - m.opacity_logits.detach()[1]) - 0.05) < 1e-3


def test_error_views_draws_a_seeded_subset():
    views = [SimpleNamespace(name=f"v{i:03d}") for i in range(220)]
    cfg = TrainConfig()
    assert error_views(views, cfg, 250) == views  # 0: every view, the paper
    cfg = replace(cfg, error_views=64)
    a, b = error_views(views, cfg, 250), error_views(views, cfg, 500)
    assert len(a) == len(set(v.name for v in a)) == 64 and a == sorted(a, key=lambda v: v.name)
    assert a == error_views(views, cfg, 250)  # a resumed run draws the same
    assert a != b  # a new draw at every routine
    assert error_views(views[:40], cfg, 250) == views[:40]  # fewer views than the cap: all of them


def test_error_pixels_hold_a_routine_to_the_same_renders_at_any_image_size():
    fast = load_config(None, preset="fast")
    # fast's pixel budget keeps the 64 views chosen at 200x133 there and below, and renders the same pixels above
    assert [resolve(fast, w * h).error_views for w, h in ((192, 128), (200, 133), (399, 266), (798, 531))] == \
        [64, 64, 16, 4]
    assert resolve(fast, 4000 * 3000).error_views == 1  # never none
    # on its own, the budget sets the views; off (0), error_views stays as written
    assert resolve(TrainConfig(error_pixels=1e6), 500 * 500).error_views == 4
    assert resolve(TrainConfig(error_views=64), 399 * 266).error_views == 64
    assert resolve(load_config(None, preset="paper"), 399 * 266).error_views == 0  # every view, the paper
