"""Tests of the pure-PyTorch reference renderer against docs/reference/renderer.md (analytic cases, finite
differences, the world-space texel property, extremes)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from scenes import (FLOAT_INPUTS, Case, cast, hand_scene, make_surfels, pinhole, quat_axis_angle, random_scene,
                    single_surfel, with_grad)

import ctgs.render.reference as ref
from ctgs.render.reference import render_reference

# float64 analytic comparisons: only rounding of a handful of ops separates the two sides.
ATOL_ANALYTIC = 1e-12
# float32 vs float64 forward on random_scene: observed worst ~2e-6 (cumprod/sum rounding); the margin
# allows for pixels near the cutoff contour whose rho rounds differently (none observed at seed 0).
ATOL_F32 = 1e-4
# Finite differences (gradcheck, eps 1e-6, float64): truncation error ~eps^2 * f''' is ~1e-10 here.
GRADCHECK_ATOL, GRADCHECK_RTOL = 1e-6, 1e-5


def _grads(out, s, seed: int = 0):
    """Gradients of a random-cotangent loss w.r.t. every float input, in FLOAT_INPUTS order."""
    g = torch.Generator().manual_seed(seed)
    loss = sum((o * torch.rand(o.shape, generator=g, dtype=o.dtype)).sum() for o in (out.rgb, out.alpha, out.depth))
    return torch.autograd.grad(loss, [getattr(s, name) for name in FLOAT_INPUTS])


def _pixel_ray(cam, x: int, y: int) -> torch.Tensor:
    return torch.tensor([(x + 0.5 - cam.cx) / cam.fx, (y + 0.5 - cam.cy) / cam.fy, 1.0], dtype=torch.float64)


# ---- analytic cases -------------------------------------------------------------------------------


def test_single_fronto_parallel_surfel_alpha_colour_depth():
    case = single_surfel(tex_res=(0, 0), textures=torch.zeros(0, 3), scale=(0.5, 0.3), opacity=0.8)
    out = render_reference(case.surfels, case.camera)
    c = 10  # centre pixel of the 21x21 image looks straight at the surfel centre
    for x, y in [(c, c), (c + 1, c), (c, c + 1), (c + 2, c - 1), (c - 3, c + 2)]:
        lx, ly = 0.2 * (x - c), 0.2 * (y - c)  # hit point: one pixel = depth/focal = 0.2 world units
        rho3d = (lx / 0.5) ** 2 + (ly / 0.3) ** 2
        rho2d = 2.0 * ((x - c) ** 2 + (y - c) ** 2)
        assert rho3d <= rho2d  # the 3D Gaussian wins at these pixels
        alpha = 0.8 * math.exp(-0.5 * rho3d)
        assert out.alpha[y, x].item() == pytest.approx(alpha, abs=ATOL_ANALYTIC)
        assert out.depth[y, x].item() == pytest.approx(alpha * 2.0, abs=ATOL_ANALYTIC)
        torch.testing.assert_close(out.rgb[y, x], torch.full((3,), 0.5 * alpha, dtype=torch.float64),
                                   atol=ATOL_ANALYTIC, rtol=0)
    # Beyond 3 sigma along v (ly = 1.2 > 3 * 0.3) nothing is drawn although o*G = 0.8*exp(-8) > 1/255.
    assert out.alpha[c + 6, c].item() == 0.0
    # Background: rgb = C + T * bg.
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out_bg = render_reference(case.surfels, case.camera, background=bg)
    torch.testing.assert_close(out_bg.rgb, out.rgb + (1 - out.alpha)[..., None] * bg, atol=1e-15, rtol=0)


def test_min_and_max_alpha():
    # opacity 1 at the centre: alpha = min(0.99, 1 * G(0) = 1) = 0.99.
    out = render_reference(single_surfel(opacity=1.0).surfels, single_surfel().camera)
    assert out.alpha[10, 10].item() == pytest.approx(0.99, abs=ATOL_ANALYTIC)
    # opacity just below 1/255: skipped everywhere; just above: drawn at the centre only.
    lo = render_reference(single_surfel(opacity=0.99 / 255).surfels, single_surfel().camera)
    hi = render_reference(single_surfel(opacity=1.01 / 255).surfels, single_surfel().camera)
    assert lo.alpha.abs().max().item() == 0.0
    assert hi.alpha[10, 10].item() == pytest.approx(1.01 / 255, abs=ATOL_ANALYTIC)


def _one_texture(values):
    """3x3 texture whose texel (iu, iv) has red offset values[iv][iu], green and blue 0."""
    t = torch.zeros(9, 3, dtype=torch.float64)
    t[:, 0] = torch.tensor(values, dtype=torch.float64).reshape(-1)
    return t


def test_texture_picks_expected_texel():
    values = [[0.01, 0.02, 0.03], [0.04, 0.05, 0.06], [0.07, 0.08, 0.09]]  # row = iv, column = iu
    case = single_surfel(texel=0.2, textures=_one_texture(values))
    out = render_reference(case.surfels, case.camera)
    excess = out.rgb[..., 0] - out.rgb[..., 1]  # = alpha * red offset (green is the bare base colour)
    c = 10
    for iv in range(3):
        for iu in range(3):
            x, y = c + iu - 1, c + iv - 1  # one pixel = one texel; texel (1, 1) at the surfel centre
            a = out.alpha[y, x].item()
            assert excess[y, x].item() == pytest.approx(a * values[iv][iu], abs=1e-12)
    # uu = 3 and uu = -1 lie outside (-1, res): texture 0 (both taps outside or weight 0).
    for x, y in [(c + 2, c), (c - 2, c), (c, c + 2), (c, c - 2)]:
        assert abs(excess[y, x].item()) < 1e-12
    # One-hot: lighting one texel at a time moves the only textured pixel accordingly.
    for r in range(9):
        onehot = [[0.0] * 3 for _ in range(3)]
        onehot[r // 3][r % 3] = 0.3
        o = render_reference(single_surfel(texel=0.2, textures=_one_texture(onehot)).surfels, case.camera)
        ex = (o.rgb[..., 0] - o.rgb[..., 1]).abs() > 1e-9
        assert ex.nonzero().tolist() == [[c + r // 3 - 1, c + r % 3 - 1]]


def test_texture_bilinear_between_texels_and_at_grid_edge():
    values = [[0.01, 0.02, 0.03], [0.04, 0.05, 0.06], [0.07, 0.08, 0.09]]
    case = single_surfel(texel=0.4, textures=_one_texture(values))  # one pixel = half a texel
    out = render_reference(case.surfels, case.camera)
    excess = (out.rgb[..., 0] - out.rgb[..., 1]) / out.alpha
    c = 10
    # uu = (x - c)/2 + 1, vv = (y - c)/2 + 1.
    assert excess[c, c + 1].item() == pytest.approx((0.05 + 0.06) / 2, abs=1e-12)  # uu=1.5, vv=1
    assert excess[c + 1, c + 1].item() == pytest.approx((0.05 + 0.06 + 0.08 + 0.09) / 4, abs=1e-12)
    assert excess[c, c + 3].item() == pytest.approx(0.06 / 2, abs=1e-12)  # uu=2.5: right tap outside
    assert excess[c, c - 3].item() == pytest.approx(0.04 / 2, abs=1e-12)  # uu=-0.5: left tap outside
    assert excess[c - 3, c - 3].item() == pytest.approx(0.01 / 4, abs=1e-12)  # corner, 3 taps outside


def test_sh_degree_one_sign_convention():
    # Surfel straight ahead: dir = (0, 0, 1), so band 1 contributes only +C1 * sh[2] (3DGS layout).
    case = single_surfel(tex_res=(0, 0), textures=torch.zeros(0, 3), opacity=0.9)
    sh = torch.zeros(1, 4, 3, dtype=torch.float64)
    sh[0, 0] = 0.1
    sh[0, 2] = torch.tensor([0.2, -0.1, 0.0])
    sh[0, 1] = sh[0, 3] = 1.0  # multiplied by y = x = 0: no effect
    s = replace(case.surfels, sh=sh)
    out = render_reference(s, case.camera)
    expected = 0.5 + 0.28209479177387814 * 0.1 + 0.4886025119029199 * sh[0, 2]
    torch.testing.assert_close(out.rgb[10, 10] / out.alpha[10, 10], expected, atol=1e-12, rtol=0)
    # sh_degree=0 ignores the higher band.
    out0 = render_reference(s, case.camera, sh_degree=0)
    torch.testing.assert_close(out0.rgb[10, 10] / out0.alpha[10, 10],
                               torch.full((3,), 0.5 + 0.28209479177387814 * 0.1, dtype=torch.float64),
                               atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="sh_degree"):
        render_reference(s, case.camera, sh_degree=2)


def test_tilted_surfel_depth_is_ray_plane_hit():
    q = quat_axis_angle((1.0, 0.4, 0.0), 0.8)
    s = make_surfels(means=[[0.1, -0.05, 2.0]], quats=[q], scales=[[0.6, 0.5]], opacities=[0.9],
                     sh=[[0.3, 0.3, 0.3]], texel_size=[0.1], tex_res=[[0, 0]], textures=torch.zeros(0, 3))
    cam = pinhole(16, 16, 12.0)
    out = render_reference(s, cam)
    R = ref.quat_to_rotmat(s.quats)[0]
    n, mu = R[:, 2], s.means[0]
    checked = 0
    for y in range(16):
        for x in range(16):
            a = out.alpha[y, x].item()
            if a == 0.0:
                continue
            d = _pixel_ray(cam, x, y)
            t = float(n @ mu / (n @ d))
            assert out.depth[y, x].item() / a == pytest.approx(t, rel=1e-12)
            checked += 1
    assert checked > 20


def test_order_by_centre_depth_then_index():
    def two(z0: float, z1: float):
        return make_surfels(means=[[0.0, 0.0, z0], [0.0, 0.0, z1]], quats=[[1, 0, 0, 0]] * 2,
                            scales=[[0.5, 0.5]] * 2, opacities=[0.6, 0.6], sh=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                            texel_size=[0.1, 0.1], tex_res=[[0, 0]] * 2, textures=torch.zeros(0, 3))

    cam = single_surfel().camera
    c0 = 0.5 + 0.28209479177387814
    for z0, z1, first in [(3.0, 2.0, 1), (2.0, 3.0, 0), (2.0, 2.0, 0)]:
        out = render_reference(two(z0, z1), cam)
        a = 0.6  # G = 1 at the centre pixel of both
        front = torch.tensor([c0, 0.5, 0.5] if first == 0 else [0.5, c0, 0.5], dtype=torch.float64)
        back = torch.tensor([0.5, c0, 0.5] if first == 0 else [c0, 0.5, 0.5], dtype=torch.float64)
        torch.testing.assert_close(out.rgb[10, 10], a * front + (1 - a) * a * back, atol=1e-12, rtol=0)


def test_t_eps_stop_rule_and_error_stats():
    # Four coincident surfels (equal depth: index order) with alpha 0.95 at the centre: T = 0.05,
    # 0.0025, 1.25e-4, then the fourth would leave 6.25e-6 < T_EPS: it is not blended (3DGS rule), so
    # its colour must not appear. Elsewhere alpha < 0.9 and (1 - alpha)^4 >= 1e-4: all four blend.
    s = make_surfels(means=[[0.0, 0.0, 2.0]] * 4, quats=[[1, 0, 0, 0]] * 4,
                     scales=[[0.5, 0.5]] * 4, opacities=[0.95] * 4,
                     sh=[[0, 0, 0], [0, 0, 0], [0, 0, 0], [5.0, 5.0, 5.0]],
                     texel_size=[0.1] * 4, tex_res=[[0, 0]] * 4, textures=torch.zeros(0, 3))
    cam = single_surfel().camera
    err = torch.rand(21, 21, dtype=torch.float64)
    out = render_reference(s, cam, error_image=err)
    assert out.alpha[10, 10].item() == pytest.approx(1 - 0.05 ** 3, abs=1e-12)
    torch.testing.assert_close(out.rgb[10, 10], torch.full((3,), 0.5 * (1 - 0.05 ** 3), dtype=torch.float64),
                               atol=1e-12, rtol=0)
    # Next pixel (rho = 0.16): no stop, the fourth (bright) one is blended behind the other three.
    a = 0.95 * math.exp(-0.5 * 0.16)
    c4 = 0.5 + 5.0 * 0.28209479177387814
    assert out.rgb[10, 11, 0].item() == pytest.approx(0.5 * (1 - (1 - a) ** 3) + c4 * a * (1 - a) ** 3, abs=1e-12)
    # Error statistics: count = pixels where blended; the fourth misses exactly the centre pixel.
    # Sum over primitives of contrib = sum of the alpha image (telescoping).
    st = out.stats
    assert st.count.dtype == torch.int32 and st.count.shape == (4,)
    assert st.count[0] == st.count[1] == st.count[2] == st.count[3] + 1 > 1
    assert st.contrib.sum().item() == pytest.approx(out.alpha.sum().item(), rel=1e-12)
    assert st.err.sum().item() == pytest.approx((err * out.alpha).sum().item(), rel=1e-12)
    assert st.contrib[3].item() < st.contrib[2].item() < st.contrib[1].item() < st.contrib[0].item()


def test_error_stats_random_scene():
    case = random_scene(30, seed=3)
    err = torch.rand(case.camera.height, case.camera.width, dtype=torch.float64)
    out = render_reference(case.surfels, case.camera, error_image=err)
    st = out.stats
    assert st.contrib.sum().item() == pytest.approx(out.alpha.sum().item(), rel=1e-10)
    assert st.err.sum().item() == pytest.approx((err * out.alpha).sum().item(), rel=1e-10)
    assert bool((st.count > 0).eq(st.contrib > 0).all())
    # e = 1 everywhere gives err == contrib; chunking does not change the statistics.
    ones = render_reference(case.surfels, case.camera, error_image=torch.ones_like(err), chunk_pairs=97)
    torch.testing.assert_close(ones.stats.err, ones.stats.contrib, atol=1e-12, rtol=0)
    torch.testing.assert_close(ones.stats.contrib, st.contrib, atol=1e-12, rtol=0)
    assert torch.equal(ones.stats.count, st.count)
    assert render_reference(case.surfels, case.camera).stats is None


# ---- the world-space texel property ---------------------------------------------------------------


def test_scaling_reveals_texture_instead_of_stretching():
    q = quat_axis_angle((0.3, 1.0, 0.2), 0.6)
    res = 12
    tex = (torch.rand(res * res, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64) - 0.5) * 0.8

    def surfel(scale: float):
        return make_surfels(means=[[0.05, 0.02, 2.0]], quats=[q], scales=[[0.3 * scale, 0.25 * scale]],
                            opacities=[0.9], sh=[[0.4, 0.3, 0.5]], texel_size=[0.07], tex_res=[[res, res]],
                            textures=tex)

    cam = pinhole(40, 40, 30.0)
    small, big = render_reference(surfel(1.0), cam), render_reference(surfel(2.0), cam)
    # Inside the small one's 1-sigma area the alpha differs but the colour (rgb/alpha) must not.
    s = surfel(1.0)
    R = ref.quat_to_rotmat(s.quats)[0]
    inside = torch.zeros(40, 40, dtype=torch.bool)
    for y in range(40):
        for x in range(40):
            d = _pixel_ray(cam, x, y)
            p = float(R[:, 2] @ s.means[0] / (R[:, 2] @ d)) * d - s.means[0]
            inside[y, x] = (float(R[:, 0] @ p) / 0.3) ** 2 + (float(R[:, 1] @ p) / 0.25) ** 2 <= 1.0
    assert inside.sum() > 30
    col_small = small.rgb[inside] / small.alpha[inside][:, None]
    col_big = big.rgb[inside] / big.alpha[inside][:, None]
    torch.testing.assert_close(col_big, col_small, atol=1e-12, rtol=0)
    assert not torch.allclose(small.alpha[inside], big.alpha[inside])
    assert col_small.std(0).min() > 0.05  # the texture really varies there (not a flat colour)
    # The big one shows texture beyond the small one's 3-sigma footprint.
    outer = (small.alpha == 0) & (big.alpha > 0)
    assert outer.sum() > 30


# ---- gradients ------------------------------------------------------------------------------------


def test_hand_scene_stays_away_from_discontinuities(monkeypatch):
    """Shifting each threshold slightly must not change the hand scene's image (else FD are invalid)."""
    case = hand_scene()
    base = render_reference(case.surfels, case.camera)
    assert base.alpha.max() < 0.95 and (base.alpha > 0).sum() > 80
    assert (1 - base.alpha).min() > 1e-2  # far from T_EPS
    for name, value in [("CUTOFF_RHO", 9.0 * (1 - 1e-3)), ("CUTOFF_RHO", 9.0 * (1 + 1e-3)),
                        ("MIN_ALPHA", 0.9 / 255), ("MIN_ALPHA", 1.1 / 255), ("MAX_ALPHA", 0.9),
                        ("T_EPS", 1e-3), ("FILTER_INV_SQUARE", 2.0 * 0.8)]:
        monkeypatch.setattr(ref, name, value)
        out = render_reference(case.surfels, case.camera)
        monkeypatch.undo()
        assert torch.equal(out.rgb, base.rgb) and torch.equal(out.alpha, base.alpha), name
    # Colour clamp: base colours plus the largest texel offset stay positive.
    assert (base.rgb >= 0).all() and (base.rgb[base.alpha > 0] > 0).all()
    assert case.surfels.textures.abs().max() < 0.26


def test_gradcheck_hand_scene_float64():
    case = hand_scene()
    s0 = case.surfels
    names = FLOAT_INPUTS

    def f(*xs):
        s = replace(s0, **dict(zip(names, xs)))
        out = render_reference(s, case.camera, chunk_pairs=64)  # several chunks: checkpointing on
        return out.rgb, out.alpha, out.depth

    inputs = tuple(getattr(s0, n).detach().clone().requires_grad_(True) for n in names)
    # fast_mode: compares v^T J u for random u, v against central differences (a full Jacobian would
    # cost one backward per output element: minutes).
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=GRADCHECK_ATOL, rtol=GRADCHECK_RTOL, fast_mode=True)


def test_gradients_reach_every_input_and_texture_does_not_feed_scales():
    case = hand_scene()
    s = with_grad(case.surfels)
    out = render_reference(s, case.camera)
    grads = dict(zip(FLOAT_INPUTS, torch.autograd.grad(out.rgb.sum(), [getattr(s, n) for n in FLOAT_INPUTS])))
    for name, g in grads.items():
        assert torch.isfinite(g).all() and g.abs().max() > 0, name
    # Texture changes move the colour only through uv = l / k: d rgb / d scales ignores the texture.
    s2 = with_grad(replace(case.surfels, textures=case.surfels.textures + 0.1))
    out2 = render_reference(s2, case.camera)
    ga = torch.autograd.grad(render_reference(s, case.camera).alpha.sum(), s.scales)[0]
    gb = torch.autograd.grad(out2.alpha.sum(), s2.scales)[0]
    torch.testing.assert_close(ga, gb, atol=0, rtol=0)


def test_chunking_and_checkpointing_do_not_change_results():
    case = random_scene(25, seed=1)
    s = with_grad(case.surfels)
    full = render_reference(s, case.camera, chunk_pairs=1 << 30)
    tiny = render_reference(s, case.camera, chunk_pairs=100)  # 4 pixels per chunk, checkpointed
    for a, b in [(full.rgb, tiny.rgb), (full.alpha, tiny.alpha), (full.depth, tiny.depth)]:
        torch.testing.assert_close(a, b, atol=1e-14, rtol=0)
    for ga, gb in zip(_grads(full, s), _grads(tiny, s)):
        torch.testing.assert_close(ga, gb, atol=1e-12, rtol=1e-12)


def test_float32_matches_float64_and_texel_size_shapes():
    case = random_scene(40, seed=0)
    out64 = render_reference(case.surfels, case.camera)
    out32 = render_reference(cast(case.surfels, torch.float32), case.camera.to("cpu", torch.float32))
    assert out32.rgb.dtype == torch.float32
    assert (out64.alpha > 0).float().mean() > 0.3  # the scene covers a good part of the image
    torch.testing.assert_close(out32.rgb.double(), out64.rgb, atol=ATOL_F32, rtol=0)
    torch.testing.assert_close(out32.alpha.double(), out64.alpha, atol=ATOL_F32, rtol=0)
    # texel_size [N] means the same size on both axes as [N, 2].
    k = case.surfels.texel_size[:, 0]
    a = render_reference(replace(case.surfels, texel_size=k), case.camera)
    b = render_reference(replace(case.surfels, texel_size=torch.stack([k, k], 1)), case.camera)
    assert torch.equal(a.rgb, b.rgb)


# ---- extremes: outputs and gradients finite ----------------------------------------------------


def _assert_finite(case, dtype=torch.float64):
    s = with_grad(cast(case.surfels, dtype))
    out = render_reference(s, case.camera.to("cpu", dtype))
    for name, t in [("rgb", out.rgb), ("alpha", out.alpha), ("depth", out.depth)]:
        assert torch.isfinite(t).all(), name
    for name, g in zip(FLOAT_INPUTS, _grads(out, s)):
        assert g.shape == getattr(s, name).shape and torch.isfinite(g).all(), name
    return out, s


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("what", ["scale", "distance", "texel"])
@pytest.mark.parametrize("mag", [1e-8, 1e-3, 1.0, 1e3, 1e8])
def test_extreme_magnitudes_stay_finite(what, mag, dtype):
    case = hand_scene()
    s = case.surfels
    if what == "scale":
        s = replace(s, scales=s.scales * mag)
    elif what == "distance":
        s = replace(s, means=s.means * mag)
    else:
        s = replace(s, texel_size=s.texel_size * mag)
    _assert_finite(replace(case, surfels=s), dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opacity_zero_and_one_and_big_textures(dtype):
    case = hand_scene()
    s = replace(case.surfels, opacities=torch.tensor([0.0, 1.0, 1.0], dtype=torch.float64))
    out, _ = _assert_finite(replace(case, surfels=s), dtype)
    assert out.alpha.max().item() <= 1 - 0.01 ** 2 + 1e-6
    # 1x1 and 256x256 textures.
    big = make_surfels(means=[[0.0, 0.0, 2.0], [0.1, 0.0, 2.5]], quats=[[1, 0, 0, 0]] * 2,
                       scales=[[0.4, 0.4]] * 2, opacities=[0.5] * 2, sh=[[0.2, 0.2, 0.2]] * 2,
                       texel_size=[0.004, 0.3], tex_res=[[256, 256], [1, 1]])
    _assert_finite(replace(case, surfels=big), dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grazing_surfel_uses_fallback_without_texture(dtype):
    # Normal along x, surfel on the optical axis: at the centre column n.d = dx = 0 (invalid hit).
    q = quat_axis_angle((0.0, 1.0, 0.0), math.pi / 2)
    s = make_surfels(means=[[0.0, 0.0, 2.0]], quats=[q], scales=[[0.3, 0.3]], opacities=[0.9],
                     sh=[[0.2, 0.2, 0.2]], texel_size=[0.05], tex_res=[[8, 8]])
    cam = pinhole(9, 9, 10.0)  # cx = 4.5: column 4 has dx = 0 exactly
    out, sg = _assert_finite(Case(s, cam), dtype)
    assert out.alpha[4, 4].item() > 0.5  # the screen-space fallback draws the edge-on surfel
    cam1 = pinhole(1, 1, 10.0)  # a 1x1 image whose only ray is exactly parallel to the plane
    out1, s1 = _assert_finite(Case(s, cam1), dtype)
    assert out1.alpha.item() > 0.5
    g_tex = torch.autograd.grad(out1.rgb.sum(), s1.textures)[0]
    assert g_tex.abs().max().item() == 0.0  # fallback won / invalid hit: no texture gradient
    # Nearly grazing (n.d ~ 1e-7, just valid or invalid): still finite.
    for angle in (math.pi / 2 - 1e-7, math.pi / 2 - 1e-5, math.pi / 2 + 1e-6):
        s2 = replace(s, quats=torch.tensor([quat_axis_angle((0.0, 1.0, 0.0), angle)], dtype=torch.float64))
        _assert_finite(Case(s2, cam), dtype)


def test_behind_camera_near_plane_empty_and_one_pixel():
    case = hand_scene()
    # All behind the camera: culled, image = background, gradients exist and are zero.
    behind = replace(case.surfels, means=case.surfels.means * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    out, s = _assert_finite(replace(case, surfels=behind))
    assert out.alpha.abs().max().item() == 0.0
    assert all(g.abs().max().item() == 0.0 for g in _grads(out, s))
    # Centre just behind the near plane: culled even though part of the surfel is in front.
    cam = replace(case.camera, near=0.5)
    straddle = make_surfels(means=[[0.0, 0.0, 0.49]], quats=[quat_axis_angle((1.0, 0.0, 0.0), 1.2)],
                            scales=[[0.3, 0.3]], opacities=[0.9], sh=[[0.2, 0.2, 0.2]], texel_size=[0.05],
                            tex_res=[[4, 4]])
    assert render_reference(straddle, cam).alpha.abs().max().item() == 0.0
    # Centre in front, tilted so the near plane cuts it: hits with t < near are dropped per pixel.
    front = replace(straddle, means=torch.tensor([[0.0, 0.0, 0.55]], dtype=torch.float64))
    out, _ = _assert_finite(Case(front, cam))
    n = ref.quat_to_rotmat(front.quats)[0][:, 2]
    for y in range(cam.height):
        for x in range(cam.width):
            d = _pixel_ray(cam, x, y)
            t = float(n @ front.means[0] / (n @ d))
            if t < 0.5:
                assert out.alpha[y, x].item() == 0.0
    assert out.alpha.max().item() > 0.1
    # N = 0 and a 1x1 image.
    empty = make_surfels(means=torch.zeros(0, 3), quats=torch.zeros(0, 4), scales=torch.zeros(0, 2),
                         opacities=torch.zeros(0), sh=torch.zeros(0, 1, 3), texel_size=torch.zeros(0),
                         tex_res=torch.zeros(0, 2), textures=torch.zeros(0, 3))
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    out = render_reference(empty, case.camera, background=bg, error_image=torch.zeros(12, 14, dtype=torch.float64))
    assert torch.equal(out.rgb, bg.expand(12, 14, 3)) and out.alpha.abs().max() == 0
    assert out.stats.count.shape == (0,)
    _assert_finite(Case(empty, case.camera))
    one = replace(case.camera, width=1, height=1, cx=0.5, cy=0.5)
    out, _ = _assert_finite(Case(case.surfels, one))
    assert out.rgb.shape == (1, 1, 3) and out.alpha.item() > 0


def test_bad_shapes_are_named():
    case = hand_scene()
    with pytest.raises(ValueError, match=r"quats must have shape \[3, 4\]"):
        render_reference(replace(case.surfels, quats=case.surfels.quats[:, :3]), case.camera)
    with pytest.raises(ValueError, match="error_image"):
        render_reference(case.surfels, case.camera, error_image=torch.zeros(3, 3))
