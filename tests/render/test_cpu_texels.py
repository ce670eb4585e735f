"""The world-space texel property on the CPU backend: scaling a primitive reveals more of its texture,
it never stretches it (paper section 3.1: texel size fixed in world units)."""

from __future__ import annotations

import torch
from scenes import make_surfels, pinhole

from ctgs.render import render


def _colour(scale: float, texel_size: float, textures, res=(16, 16)):
    s = make_surfels(means=[[0.0, 0.0, 2.0]], quats=[[1.0, 0.0, 0.0, 0.0]], scales=[[scale, scale]],
                     opacities=[0.98], sh=[[0.0, 0.0, 0.0]], texel_size=[texel_size], tex_res=[list(res)],
                     textures=textures)
    out = render(s, pinhole(41, 41, 20.0), backend="cpu")  # one pixel = 0.1 world units at depth 2
    return out.rgb / out.alpha.clamp_min(1e-12)[..., None], out.alpha  # un-premultiplied colour


def test_scaling_a_primitive_keeps_the_colour_at_each_world_point():
    g = torch.Generator().manual_seed(0)
    tex = (torch.rand(256, 3, generator=g, dtype=torch.float64) - 0.5) * 0.8
    c_small, a_small = _colour(0.2, 0.1, tex)
    c_big, a_big = _colour(0.6, 0.1, tex)
    both = (a_small > 0.05) & (a_big > 0.05)
    assert both.sum() >= 25 and (a_big > 0.05).sum() > 4 * (a_small > 0.05).sum()  # bigger: more visible
    torch.testing.assert_close(c_small[both], c_big[both], atol=1e-12, rtol=0)  # same colour, same point
    # The texture really varies over those pixels (the comparison is not between constants).
    assert c_small[both].std(0).min() > 0.05
    # Stretching the texture with the scale (texel size proportional to scale) would change the colours.
    c_stretch, _ = _colour(0.6, 0.3, tex)
    assert (c_stretch[both] - c_small[both]).abs().max() > 0.05


def test_texel_centres_at_integer_coordinates():
    """uu = lx/k + (res-1)/2: the surfel centre hits the middle of the grid; with res 3 and one texel per
    pixel, the pixel at the centre shows texel (1, 1) exactly and its neighbour texel (2, 1)."""
    tex = torch.zeros(9, 3, dtype=torch.float64)
    tex[4] = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)  # (iu=1, iv=1)
    tex[5] = torch.tensor([-0.1, 0.25, 0.2], dtype=torch.float64)  # (iu=2, iv=1)
    c, _ = _colour(0.5, 0.1, tex, res=(3, 3))
    torch.testing.assert_close(c[20, 20], 0.5 + tex[4], atol=1e-12, rtol=0)
    torch.testing.assert_close(c[20, 21], 0.5 + tex[5], atol=1e-12, rtol=0)
