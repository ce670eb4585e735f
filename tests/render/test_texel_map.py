"""The texel maps (ctgs.render.texel_map): each surfel's texel size in pixels and texture resolution on fixed log2
scales, blended with the colour render's weights and coloured with Turbo; untextured surfels grey."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ctgs.model.surfels import jagged_offsets
from ctgs.render import render
from ctgs.render.camera import Camera
from ctgs.render.texel_map import (TEXEL_PX_LOG2, TEXRES_LOG2, TURBO, UNTEXTURED, blend, compose, legend,
                                   render_map, surfel_values, turbo, value_of)
from ctgs.render.types import SurfelInputs

W, H, F, DEPTH = 96, 48, 48.0, 4.0
# Worst colour difference at a surfel's centre pixel from the exact formula: float32 blending of one surfel.
TOL = 1e-4


def camera(z: float = 0.0) -> Camera:
    """At (0, 0, z) looking down +z (the identity viewmat, moved)."""
    view = torch.eye(4)
    view[2, 3] = -z
    return Camera(fx=F, fy=F, cx=W / 2, cy=H / 2, width=W, height=H, viewmat=view, near=0.01)


def three_surfels(texels=(32.0, 1.0, 4.0), res=((16, 16), (2, 2), (0, 0)), seed: int = 0) -> SurfelInputs:
    """Three opaque surfels facing the camera at x = -1, 0, 1, depth DEPTH: texel sizes giving `texels` pixels each
    (seen from camera()), textures of `res` (the third untextured by default)."""
    g = torch.Generator().manual_seed(seed)
    n = 3
    tex_res = torch.tensor(res, dtype=torch.int32)
    k = torch.tensor(texels) * DEPTH / F  # world units per texel
    t = int((tex_res[:, 0] * tex_res[:, 1]).sum())
    return SurfelInputs(
        means=torch.tensor([[-1.0, 0.0, DEPTH], [0.0, 0.0, DEPTH], [1.0, 0.0, DEPTH]]),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n), scales=torch.full((n, 2), 0.15),
        opacities=torch.full((n,), 1.0), sh=torch.randn(n, 1, 3, generator=g),
        texel_size=torch.stack([k, k], -1), textures=torch.rand(t, 3, generator=g) * 2 - 1, tex_res=tex_res,
        tex_offset=jagged_offsets(tex_res))


def centre_pixels() -> list[tuple[int, int]]:
    """(row, column) of each surfel's centre pixel."""
    return [(H // 2, int(W / 2 + F * x / DEPTH)) for x in (-1.0, 0.0, 1.0)]


def _alpha(inputs: SurfelInputs, cam: Camera) -> torch.Tensor:
    return render(inputs, cam, backend="reference", sh_degree=0).alpha


def t_of(px: float) -> float:
    lo, hi = TEXEL_PX_LOG2
    return (math.log2(px) - lo) / (hi - lo)


def test_turbo_table_is_googles_turbo_map():
    cv2 = pytest.importorskip("cv2")
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1] / 255.0
    ours = turbo(torch.linspace(0, 1, 256, dtype=torch.float64)).numpy()
    assert np.abs(ours - lut).max() < 0.03
    assert np.allclose(turbo(torch.tensor([0.0, 1.0, -3.0, 7.0])).numpy(), TURBO[[0, -1, 0, -1]], atol=1e-6)


def test_texel_size_map_colours_each_surfel_by_its_texels_in_pixels():
    inputs, cam = three_surfels(), camera()
    t, textured = surfel_values(inputs, cam, "texel_size")
    assert np.allclose(t[:2].numpy(), [t_of(32.0), t_of(1.0)], atol=1e-6) and textured.tolist() == [True, True, False]
    pic, alpha = render_map(inputs, cam, "texel_size", backend="reference"), _alpha(inputs, cam)
    for (y, x), want in zip(centre_pixels()[:2], (t_of(32.0), t_of(1.0))):
        a = float(alpha[y, x])
        assert a > 0.5
        expect = turbo(torch.tensor(want)).numpy() * a
        assert np.abs(pic[y, x].numpy() - expect).max() < TOL, (y, x)
    y, x = centre_pixels()[2]  # untextured: grey, as covered
    assert np.allclose(pic[y, x].numpy(), UNTEXTURED * float(alpha[y, x]), atol=TOL)
    assert float(pic[0, 0].abs().max()) == 0.0  # nothing drawn: black
    # large texels read red, small ones blue
    (ya, xa), (yb, xb) = centre_pixels()[:2]
    assert pic[ya, xa, 0] > pic[ya, xa, 2] and pic[yb, xb, 2] > pic[yb, xb, 0]


def test_the_texel_size_map_follows_the_distance_and_ignores_colours_and_texel_values():
    near, far = camera(z=2.0), camera()  # twice as close: every texel twice as many pixels
    t_far = surfel_values(three_surfels(), far, "texel_size")[0]
    t_near = surfel_values(three_surfels(), near, "texel_size")[0]
    assert np.allclose((t_near - t_far)[:2].numpy(), 1.0 / (TEXEL_PX_LOG2[1] - TEXEL_PX_LOG2[0]), atol=1e-6)
    a = render_map(three_surfels(seed=0), far, "texel_size", backend="reference")
    b = render_map(three_surfels(seed=1), far, "texel_size", backend="reference")  # other SH and texel values
    assert torch.equal(a, b)


def test_texture_resolution_map_colours_each_surfel_by_its_texel_count():
    inputs, cam = three_surfels(), camera()
    t, _ = surfel_values(inputs, cam, "texture_res")
    lo, hi = TEXRES_LOG2
    assert np.allclose(t[:2].numpy(), [(8 - lo) / (hi - lo), (2 - lo) / (hi - lo)])
    pic, alpha = render_map(inputs, cam, "texture_res", backend="reference"), _alpha(inputs, cam)
    (y, x) = centre_pixels()[0]
    assert np.abs(pic[y, x].numpy() - turbo(t[0]).numpy() * float(alpha[y, x])).max() < TOL


def test_compose_takes_the_weighted_mean_over_textured_surfels_and_greys_the_rest():
    # two layers: w 0.3 at t 0.2 (textured), then w 0.5 at t 0.8 (textured), w 0.1 untextured
    r = torch.tensor([[0.3 * 0.2 + 0.5 * 0.8]])
    g = torch.tensor([[0.8]])
    a = torch.tensor([[0.9]])
    mean = (0.3 * 0.2 + 0.5 * 0.8) / 0.8
    expect = turbo(torch.tensor(mean)) * 0.8 + UNTEXTURED * 0.1
    assert torch.allclose(compose(r, g, a)[0, 0], expect, atol=1e-6)
    assert torch.equal(compose(torch.zeros(1, 1), torch.zeros(1, 1), torch.zeros(1, 1)), torch.zeros(1, 1, 3))


def test_cpu_backend_draws_the_same_map_as_the_reference():
    inputs, cam = three_surfels(), camera()
    ref = render_map(inputs, cam, "texel_size", backend="reference")
    cpu = render_map(inputs, cam, "texel_size", backend="cpu")
    assert (ref - cpu).abs().max() < 1e-4


def test_the_blended_mean_reads_back_as_pixels_and_texels():
    inputs, cam = three_surfels(), camera()
    for which, want in (("texel_size", (32.0, 1.0)), ("texture_res", (256.0, 4.0))):
        r, g, _ = blend(inputs, cam, which, backend="reference")
        for (y, x), v in zip(centre_pixels()[:2], want):
            assert float(value_of(r[y, x] / g[y, x], which)) == pytest.approx(v, rel=1e-4), which


@pytest.mark.parametrize("which", ["texel_size", "texture_res"])
def test_the_legend_is_the_scale_with_its_values_written_under_it(which):
    img = legend(which, 300, 28)
    assert img.shape == (28, 300, 3) and img.dtype == np.float32
    assert np.abs(img[2, 0] - TURBO[0]).max() < 0.01 and np.abs(img[2, -1] - TURBO[-1]).max() < 0.01
    assert img[14:].max() > 0.9  # white text under the bar
