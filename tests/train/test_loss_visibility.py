"""The texture regulariser's visibility is the rasterizer's culling (the authors' `radii > 0`), and the
transmittance-weighted variant regularises hidden primitives more."""

from __future__ import annotations

import math

import pytest
import torch

import train_helpers as th
from ctgs.model.surfels import SurfelModel, jagged_offsets
from ctgs.ops.ext import load_cpu
from ctgs.render import render
from ctgs.render.camera import Camera
from ctgs.render.constants import MIN_ALPHA
from ctgs.render.preprocess import to_camera_space
from ctgs.train.config import TrainConfig
from ctgs.train.step.loss import mean_transmittance, rasterized_mask, texture_weights, training_loss

W, H = 40, 30


def _scene(n: int, seed: int) -> tuple[SurfelModel, Camera]:
    """Surfels all around a camera at the origin: behind it, straddling the near plane, off-screen, huge,
    tiny, tilted, opacities on both sides of MIN_ALPHA."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    means = (r(n, 3) - 0.5) * torch.tensor([8.0, 6.0, 6.0]) + torch.tensor([0.0, 0.0, 1.5])
    log_scales = math.log(0.02) + r(n, 2) * math.log(150.0)  # 0.02 .. 3 world units
    o = torch.where(r(n) < 0.2, MIN_ALPHA * (0.5 + r(n)), r(n))  # many just below / above 1/255
    tex_res = torch.full((n, 2), 2, dtype=torch.int32)
    model = SurfelModel(
        means=means, log_scales=log_scales, quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.logit(o.clamp(1e-6, 1 - 1e-6)), sh=torch.rand(n, 1, 3, generator=g),
        textures_raw=torch.randn(4 * n, 3, generator=g), k_min=torch.full((n,), 0.05),
        t2p_exp=torch.ones(n, dtype=torch.int32), tex_res=tex_res, tex_offset=jagged_offsets(tex_res),
        texture_mode="content_aware")
    cam = Camera(fx=30.0, fy=31.0, cx=W / 2 + 0.4, cy=H / 2 - 0.3, width=W, height=H, viewmat=torch.eye(4),
                 near=0.2)
    return model, cam


def _binned(model: SurfelModel, cam: Camera) -> set[int]:
    """Indices the CPU kernel puts in its per-tile lists (what it rasterizes)."""
    s = model.render_inputs()
    p = to_camera_space(s.means, s.quats, s.sh, cam, 0)
    load_cpu()
    out = torch.ops.ctgs.rasterize_forward(
        p.mu_c.contiguous(), p.Rc.contiguous(), s.scales.contiguous(), s.opacities.contiguous(), p.colors.contiguous(),
        s.texel_size.contiguous(), s.textures.contiguous(), s.tex_res.contiguous(), s.tex_offset.contiguous(),
        torch.zeros(3), cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.near, None, 1, False)
    return set(out[6].tolist())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mask_is_exactly_the_rasterizers_binning(seed):
    model, cam = _scene(400, seed)
    with torch.no_grad():
        mask = rasterized_mask(model, cam)
    binned = _binned(model, cam)
    assert set(torch.nonzero(mask).flatten().tolist()) == binned
    # The scene exercises every rule: culled behind / too transparent, off-screen, and kept.
    mu_z = model.means[:, 2]
    assert 50 < len(binned) < 350, len(binned)
    assert bool(((mu_z < cam.near) & ~mask).any()) and bool(((model.opacities < MIN_ALPHA) & ~mask).any())
    # Whatever the renderer blends anywhere was kept (its statistics only count kept primitives).
    out = render(model.render_inputs(), cam, backend="cpu", error_image=torch.zeros(H, W))
    stats = out.stats
    assert bool(mask[stats.count > 0].all())
    assert int((stats.count > 0).sum()) < int(mask.sum())  # kept is conservative: some touch no pixel
    # The render's own mask (what the trainer passes to the loss) is the same set, with or without stats.
    assert torch.equal(out.rasterized, mask)
    assert torch.equal(render(model.render_inputs(), cam, backend="cpu").rasterized, mask)


def test_centre_off_screen_but_surfel_on_screen_is_regularised():
    # The old rule (centre projects into the image) missed this surfel; its texels show in the image.
    m = th.model([[-1.2, 0.0, 2.0]], [[0.5, 0.5]], [0.9], [[4, 4]])
    cam = th.camera()
    assert abs(cam.fx * -1.2 / 2.0 + cam.cx) > 0 and cam.fx * -1.2 / 2.0 + cam.cx < 0  # centre left of the image
    assert bool(rasterized_mask(m, cam)[0])
    img = th.image(m)
    assert float(img[:, :4].sum()) > 0  # and it is drawn


def _two_layer(front_opacity: float):
    """A wide surfel in front (pixels x < 35), a small one right behind it (x ~ 17 +- 6 px) and a small one
    beside it (x ~ 56 +- 6 px, unoccluded)."""
    return th.model([[-0.5, 0.0, 2.0], [-0.75, 0.0, 3.0], [1.2, 0.0, 3.0]], [[0.2, 0.2], [0.1, 0.1], [0.1, 0.1]],
                    [front_opacity, 0.8, 0.8], [[4, 4]] * 3)


def test_mean_transmittance_estimate():
    m = _two_layer(0.9)
    stats = render(m.render_inputs(), th.camera(), backend="cpu", error_image=torch.zeros(th.H, th.W)).stats
    t = mean_transmittance(stats, m.opacities)
    # Unoccluded surfels: T = 1 wherever they are blended (observed 1.00 and 1.00, clamped from 1.009).
    # Behind the front one, T = 1 - alpha_front: its plain mean over the back surfel's 112 pixels is 0.290
    # (alpha maps of each surfel alone); the estimate is the alpha-weighted mean, which leans to the
    # centre where the front surfel is denser: observed 0.188.
    assert t[0] > 0.95 and t[2] > 0.95, t
    assert 0.1 < t[1] < 0.3, t


def test_transmittance_weighting_regularises_hidden_primitives_more():
    m = _two_layer(0.9)
    cfg = TrainConfig(lambda_texture=1e-3)
    plain = texture_weights(m, th.camera(), cfg)
    assert torch.equal(plain, torch.ones(3))
    cfg.texture_reg_transmittance = True
    w = texture_weights(m, th.camera(), cfg)
    assert w[1] > 0.7 and w[0] < 0.05 and w[2] < 0.05, w  # observed 0.81, 0, 0
    # Stats passed by the caller give the same weights as the extra render.
    stats = render(m.render_inputs(), th.camera(), backend="cpu", error_image=torch.zeros(th.H, th.W)).stats
    assert torch.equal(texture_weights(m, th.camera(), cfg, stats), w)
    # And the loss term is lambda * sum_i w_i * sum |texels of i|.
    gt = torch.full((th.H, th.W, 3), 0.5)
    off = TrainConfig(lambda_texture=0.0)
    sizes = (m.tex_res[:, 0] * m.tex_res[:, 1]).long()
    per_prim = torch.zeros(3).index_add_(0, torch.repeat_interleave(torch.arange(3), sizes),
                                         m.textures.detach().abs().sum(1))
    with torch.no_grad():
        term = float(training_loss(gt, gt, m, th.camera(), cfg).total - training_loss(gt, gt, m, th.camera(), off).total)
    assert abs(term - 1e-3 * float((w * per_prim).sum())) < 1e-6


def test_loss_with_the_renders_mask_equals_the_recomputed_one():
    model, cam = _scene(300, 5)
    model.textures_raw.requires_grad_(True)
    cfg = TrainConfig(lambda_texture=0.5)
    out = render(model.render_inputs(), cam, backend="cpu")
    gt = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0))
    a = training_loss(out.rgb, gt, model, cam, cfg, rasterized=out.rasterized).total
    b = training_loss(out.rgb, gt, model, cam, cfg).total
    assert torch.equal(a, b)
