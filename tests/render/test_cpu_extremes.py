"""Extreme inputs on the C++ CPU backend: outputs and gradients stay finite (and agree with the reference
in float64 where both are defined), every pixel is written (outputs poisoned with NaN first)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from scenes import FLOAT_INPUTS, make_surfels, pinhole, quat_axis_angle, with_grad

import ctgs.render.api as api
from ctgs.render import render

MAGNITUDES = (1e-8, 1e-4, 1.0, 1e4, 1e8)
# float64 agreement with the reference on these degenerate scenes: same formulas, different order;
# observed worst 1e-15 (images) and 3e-14 relative (gradients).
ATOL_IMG = 1e-10
GRAD_RTOL = 1e-9


@pytest.fixture(autouse=True)
def _poison(monkeypatch):
    monkeypatch.setattr(api, "POISON_OUTPUTS", True)


def _surfel(dtype, *, depth=2.0, scale=0.5, texel=0.1, opacity=0.8, quat=(1.0, 0.0, 0.0, 0.0), res=(6, 6),
            x=0.0):
    return make_surfels(means=[[x, 0.0, depth], [0.2 + x, 0.1, depth * 1.3]],
                        quats=[list(quat), quat_axis_angle((0.3, 1.0, 0.0), 0.4)],
                        scales=[[scale, scale * 0.7], [scale * 0.8, scale]], opacities=[opacity, 0.5],
                        sh=[[0.3, 0.2, 0.1], [0.1, 0.4, 0.2]], texel_size=[texel, texel * 1.3],
                        tex_res=[list(res), [3, 2]], dtype=dtype, seed=3)


def _check(s, cam, dtype, compare=True):
    """Render with grads on the CPU backend; all finite; optionally equal to the reference (float64)."""
    sg = with_grad(s)
    out = render(sg, cam, backend="cpu")
    for name in ("rgb", "alpha", "depth"):
        t = getattr(out, name)
        assert t.dtype == dtype and torch.isfinite(t).all(), name
    loss = out.rgb.sum() + 0.3 * out.alpha.sum() + 0.01 * out.depth.sum()
    grads = torch.autograd.grad(loss, [getattr(sg, n) for n in FLOAT_INPUTS], allow_unused=True)
    for name, g in zip(FLOAT_INPUTS, grads):
        assert g is not None and g.shape == getattr(sg, name).shape, name
        assert torch.isfinite(g).all(), name
    if compare and dtype == torch.float64:
        sr = with_grad(s)
        ref = render(sr, cam, backend="reference")
        for name in ("rgb", "alpha", "depth"):
            torch.testing.assert_close(getattr(out, name), getattr(ref, name), atol=ATOL_IMG, rtol=1e-12)
        rl = ref.rgb.sum() + 0.3 * ref.alpha.sum() + 0.01 * ref.depth.sum()
        rg = torch.autograd.grad(rl, [getattr(sr, n) for n in FLOAT_INPUTS])
        for name, x, y in zip(FLOAT_INPUTS, grads, rg):
            tol = GRAD_RTOL * max(y.abs().max().item(), 1e-30) if y.numel() else 0
            assert (x - y).abs().max().item() <= tol if y.numel() else True, name
    return out


DTYPES = [torch.float32, torch.float64]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("mag", MAGNITUDES)
def test_scale_magnitudes(dtype, mag):
    _check(_surfel(dtype, scale=mag), pinhole(24, 20, 20.0).to("cpu", dtype), dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("mag", MAGNITUDES)
def test_distance_magnitudes(dtype, mag):
    # Scale grows with distance so the surfel stays about the same size on screen (1e-8: culled by near).
    _check(_surfel(dtype, depth=mag, scale=0.2 * mag, texel=0.05 * mag), pinhole(24, 20, 20.0, near=1e-9 if
           mag < 1e-2 else 0.01).to("cpu", dtype), dtype, compare=mag >= 1e-4)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("mag", MAGNITUDES)
def test_texel_size_magnitudes(dtype, mag):
    out = _check(_surfel(dtype, texel=mag), pinhole(24, 20, 20.0).to("cpu", dtype), dtype)
    assert out.alpha.max() > 0.5


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("opacity", [0.0, 1.0])
def test_opacity_zero_and_one(dtype, opacity):
    out = _check(_surfel(dtype, opacity=opacity), pinhole(24, 20, 20.0).to("cpu", dtype), dtype)
    assert out.alpha.max() <= 0.99 + 0.99 * 0.01 + 1e-6  # two layers of at most MAX_ALPHA


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle_deg", [89.0, 89.9999, 90.0])
def test_grazing_angles(dtype, angle_deg):
    """n.d -> 0: the plane hit becomes invalid and the screen-space fallback takes over (no texture)."""
    q = quat_axis_angle((0.0, 1.0, 0.0), math.radians(angle_deg))
    out = _check(_surfel(dtype, quat=q), pinhole(24, 20, 20.0).to("cpu", dtype), dtype)
    assert out.alpha.max() > 0  # the fallback keeps an edge-on surfel visible


@pytest.mark.parametrize("dtype", DTYPES)
def test_behind_camera_and_straddling_near_plane(dtype):
    s = make_surfels(
        means=[[0.0, 0.0, -1.0], [0.1, 0.0, 0.3], [0.0, 0.1, 0.011], [0.0, 0.0, 1.5]],
        # [1]: big surfel tilted 70 degrees: its 3-sigma corners cross z = near; [2]: centre just past near.
        quats=[[1.0, 0.0, 0.0, 0.0], quat_axis_angle((0.0, 1.0, 0.0), 1.2), quat_axis_angle((1.0, 0.0, 0.0), 0.3),
               [1.0, 0.0, 0.0, 0.0]],
        scales=[[1.0, 1.0], [0.6, 0.2], [0.5, 0.5], [0.4, 0.4]], opacities=[0.9, 0.8, 0.7, 0.6],
        sh=[[0.3, 0.2, 0.1]] * 4, texel_size=[0.05] * 4, tex_res=[[4, 4]] * 4, dtype=dtype, seed=4)
    out = _check(s, pinhole(32, 24, 25.0, near=0.01).to("cpu", dtype), dtype)
    assert out.alpha.max() > 0.5


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("res", [(1, 1), (256, 256), (1, 7)])
def test_texture_resolutions(dtype, res):
    _check(_surfel(dtype, res=res, texel=1.0 / max(res)), pinhole(24, 20, 20.0).to("cpu", dtype), dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_no_texels_at_all(dtype):
    s = _surfel(dtype, res=(0, 0))
    s = replace(s, tex_res=torch.zeros(2, 2, dtype=torch.int32), tex_offset=torch.zeros(2, dtype=torch.int64),
                textures=torch.zeros(0, 3, dtype=dtype))
    _check(s, pinhole(24, 20, 20.0).to("cpu", dtype), dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_empty_scene(dtype):
    s = make_surfels(means=torch.zeros(0, 3), quats=torch.zeros(0, 4), scales=torch.zeros(0, 2),
                     opacities=torch.zeros(0), sh=torch.zeros(0, 1, 3), texel_size=torch.zeros(0),
                     tex_res=torch.zeros(0, 2), dtype=dtype)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype, requires_grad=True)
    sg = with_grad(s)
    err = torch.ones(20, 24, dtype=dtype)
    out = render(sg, pinhole(24, 20, 20.0).to("cpu", dtype), backend="cpu", background=bg, error_image=err)
    assert torch.equal(out.rgb, bg.detach().expand(20, 24, 3))
    assert out.alpha.abs().max() == 0 and out.depth.abs().max() == 0
    assert out.stats.count.shape == (0,)
    (g_bg, g_means) = torch.autograd.grad(out.rgb.sum(), [bg, sg.means])
    assert torch.equal(g_bg, torch.full((3,), 480.0, dtype=dtype)) and g_means.shape == (0, 3)


@pytest.mark.parametrize("dtype", DTYPES)
def test_one_pixel_image(dtype):
    out = _check(_surfel(dtype), pinhole(1, 1, 2.0).to("cpu", dtype), dtype)
    assert out.rgb.shape == (1, 1, 3) and out.alpha.item() > 0.5


def test_empty_tiles_are_written():
    """A 100x70 image (partial tiles on both axes) where most tiles hold no primitive: with NaN-poisoned
    buffers, any pixel the kernel skipped would stay NaN."""
    s = _surfel(torch.float32, scale=0.05)
    out = render(s, pinhole(100, 70, 50.0).to("cpu", torch.float32), backend="cpu")
    assert api.POISON_OUTPUTS
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.alpha).all() and torch.isfinite(out.depth).all()
    assert (out.alpha == 0).float().mean() > 0.9
