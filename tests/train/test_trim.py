"""texture_trim: textures cropped to the texels that hold something (ctgs.train.routines.texels.trim)."""

from __future__ import annotations

import math

import pytest
import torch

from ctgs.model import jagged
from ctgs.render import render
from ctgs.train.config import TrainConfig
from ctgs.train.routines import texels

from train_helpers import camera, image, model, optimiser


def _raw(act: torch.Tensor) -> torch.Tensor:
    """Raw texels whose activation 2 sigmoid(raw) - 1 is act (|act| < 1)."""
    return torch.logit((act + 1) / 2)


def _three(res: int = 8):
    """Surfel 0: content only in its central 2x2 texels; 1: no content (raw 0); 2: content in a corner texel."""
    a0 = torch.zeros(res, res, 3)
    a0[res // 2 - 1: res // 2 + 1, res // 2 - 1: res // 2 + 1] = torch.tensor([0.5, -0.4, 0.3])
    a2 = torch.zeros(res, res, 3)
    a2[0, res - 1, 1] = -0.6
    tex = torch.cat([_raw(a0).reshape(-1, 3), torch.zeros(res * res, 3), _raw(a2).reshape(-1, 3)])
    return model(means=[[-0.3, 0.0, 3.0], [0.3, 0.1, 3.5], [0.0, -0.2, 3.2]],
                 scales=[[0.2, 0.15], [0.15, 0.2], [0.12, 0.12]], opacities=[0.9, 0.8, 0.7],
                 tex_res=[[res, res]] * 3, textures=tex)


def test_trim_crops_symmetrically_drops_empty_and_keeps_image():
    m = _three()
    opt = optimiser(m)
    before = image(m)
    old0 = jagged.blocks(m.textures_raw.detach(), m.tex_offset, torch.tensor([0]), 8, 8)[0]
    old2 = m.textures_raw.detach()[128:192].clone()
    stats = texels.trim(m, opt, 0.004)
    assert m.tex_res.tolist() == [[2, 2], [0, 0], [8, 8]]
    assert stats == {"textures_dropped": 1, "texels_before": 192, "texels_after": 4 + 64}
    # The kept texels are the same values at the same places (a symmetric crop keeps texel centres).
    blk0 = jagged.blocks(m.textures_raw.detach(), m.tex_offset, torch.tensor([0]), 2, 2)[0]
    assert torch.equal(blk0, old0[3:5, 3:5])
    assert torch.equal(m.textures_raw.detach()[4:], old2)
    # Adam moments moved with them (optimiser() sets the first moment to the texel values).
    assert torch.equal(opt.exp_avg["textures_raw"], m.textures_raw.detach())
    # Everything dropped was exactly 0 here, so the image is the same up to float rounding.
    assert float((image(m) - before).abs().max()) < 1e-6


@pytest.mark.parametrize("eps", [1e-7, 0.004, 0.05, 0.5])
def test_trim_moves_no_rendered_value_by_eps(eps):
    # Texels of every magnitude: small ones (that go) next to large ones, at random places.
    g = torch.Generator().manual_seed(1)
    res = 12
    act = torch.randn(3 * res * res, 3, generator=g) * torch.logspace(-4, -0.3, 3 * res * res)[
        torch.randperm(3 * res * res, generator=g)][:, None]
    act = act.clamp(-0.95, 0.95)
    # Borders of surfel 1 small, so some crops do happen at every eps above 1e-4.
    blk = act[res * res: 2 * res * res].view(res, res, 3)
    blk[:2] *= 1e-3
    blk[-2:] *= 1e-3
    blk[:, :2] *= 1e-3
    blk[:, -2:] *= 1e-3
    m = model(means=[[-0.2, 0.0, 3.0], [0.25, 0.1, 3.2], [0.0, -0.15, 3.4]],
              scales=[[0.25, 0.2], [0.2, 0.25], [0.3, 0.2]], opacities=[0.9, 0.85, 0.8],
              tex_res=[[res, res]] * 3, textures=_raw(act))
    before = image(m)
    stats = texels.trim(m, None, eps)
    change = float((image(m) - before).abs().max())
    assert change < eps
    if eps >= 0.004:
        assert stats["texels_after"] < stats["texels_before"]
    # Every remaining texture still reaches eps on its outermost row or column (nothing left to crop).
    assert torch.equal(texels.trim_res(m, eps), m.tex_res)


def test_trim_extremes():
    m = _three()
    tex0 = m.textures_raw.detach().clone()
    assert texels.trim(m, None, 0.0)["texels_after"] == 192  # off
    assert torch.equal(m.textures_raw.detach(), tex0)
    # Just above the largest |offset| (0.6): every texture goes and the image is the untextured one exactly.
    untextured = model(means=m.means.detach(), scales=m.scales.detach(), opacities=m.opacities.detach(),
                       tex_res=[[0, 0]] * 3, textures=torch.zeros(0, 3))
    texels.trim(m, None, 0.61)
    assert m.num_texels == 0 and int(m.tex_res.abs().sum()) == 0
    assert torch.equal(image(m), image(untextured))


def test_trim_is_idempotent_and_opt_free_path_agrees():
    a, b = _three(), _three()
    texels.trim(a, optimiser(a), 0.004)
    texels.trim(b, None, 0.004)
    assert torch.equal(a.tex_res, b.tex_res) and torch.equal(a.textures_raw.detach(), b.textures_raw.detach())
    res, tex = a.tex_res.clone(), a.textures_raw.detach().clone()
    assert texels.trim(a, None, 0.004)["texels_after"] == a.num_texels
    assert torch.equal(a.tex_res, res) and torch.equal(a.textures_raw.detach(), tex)


def test_trimmed_mixed_model_renders_alike_on_cpu_and_reference():
    m = _three()
    texels.trim(m, None, 0.004)
    with torch.no_grad():
        cpu = render(m.render_inputs(), camera(), backend="cpu", sh_degree=0).rgb
        ref = render(m.render_inputs(), camera(), backend="reference", sh_degree=0).rgb
    assert float((cpu - ref).abs().max()) < 1e-5


def test_trim_skips_baselines_and_checks_config():
    m = _three()
    m.texture_mode = "fixed"
    assert texels.trim(m, None, 0.5)["texels_after"] == 192
    for bad in (-0.1, 1.0, math.nan):
        with pytest.raises(Exception, match="texture_trim"):
            TrainConfig(texture_trim=bad).validate()
