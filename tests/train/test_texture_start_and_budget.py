"""Texture start (t2p so the extent is ~8 texels, min exponent), allocation rule, split budget, init."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ctgs.train.routines import texels
from ctgs.train.routines.split import split
from ctgs.train.start.init import farthest_point_subsample, init_model

from train_helpers import image, model, optimiser


def test_texture_start_sets_about_8_texels_and_allocates_zero_textures():
    m = model(means=[[0.0, 0.0, 3.0], [0.5, 0.0, 3.0], [0, 0.3, 3.0]], scales=[[0.2, 0.2], [0.003, 0.003], [0.2, 0.1]],
              opacities=[0.9, 0.9, 0.9], tex_res=[[0, 0]] * 3, textures=torch.zeros(0, 3), k_min=[0.002] * 3)
    opt = optimiser(m)
    before = image(m)
    texels.start_textures(m, opt, start_texels=8, min_exp=1, cap=256)
    extent = 2 * texels.active_half_extent(m).min(1).values  # the paper: the SMALLEST axis is ~8 texels
    k = texels.texel_size(m)
    # Prim 0: extent ~1.2 / (8 * 0.002) = 75 -> 2^6 = 64 (nearest power of two); prim 1 hits the minimum.
    # Prim 2 (scales 0.2 x 0.1): its smaller extent 0.6 / (8 * 0.002) = 37.5 -> 2^5.
    assert m.t2p_exp.tolist() == [6, 1, 5]
    for i in (0, 2):
        assert 8 / 2 ** 0.5 <= float(extent[i] / k[i]) <= 8 * 2 ** 0.5
    # Allocation: active extent + 1 texel padding, power of two, zero offsets -> image unchanged.
    # Prim 2: 1.2 / 0.064 = 18.75 -> 32 along u, 0.6 / 0.064 = 9.4 -> 16 along v.
    assert m.tex_res[0].tolist() == [16, 16] and m.tex_res[2].tolist() == [32, 16]
    assert float(m.textures_raw.detach().abs().sum()) == 0.0
    assert torch.abs(image(m) - before).max() < 1e-6


def test_allocation_is_capped_at_256():
    m = model(means=[[0.0, 0.0, 3.0]], scales=[[5.0, 0.0003]], opacities=[0.9], tex_res=[[2, 2]], k_min=[0.001])
    assert texels.needed_res(m, 256)[0].tolist() == [256, 2]


def test_split_respects_the_primitive_budget():
    means = [[x, 0.0, 3.0] for x in np.linspace(-1, 1, 4)]
    m = model(means=means, scales=[[0.3, 0.05]] * 4, opacities=[0.9] * 4, tex_res=[[2, 2]] * 4, k_min=[0.005] * 4)
    opt = optimiser(m)
    prio = torch.tensor([0.1, 0.4, 0.3, 0.2])
    n, _ = split(m, opt, torch.ones(4, dtype=torch.bool), tau=4.0, max_primitives=6, priority=prio)
    assert n == 2 and m.num_primitives == 6
    # The two with the largest priority were split (their parents are gone).
    xs = sorted(round(v, 4) for v in m.means[:, 0].tolist())
    assert round(float(np.linspace(-1, 1, 4)[1]), 4) not in xs and round(float(np.linspace(-1, 1, 4)[2]), 4) not in xs


def test_init_from_points():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (500, 3)).astype(np.float32)
    cols = rng.uniform(0, 1, (500, 3)).astype(np.float32)
    idx = farthest_point_subsample(pts, 50)
    assert len(set(idx.tolist())) == 50
    # Farthest-point: the subset spreads out (min pairwise distance beats a random subset's).
    d = lambda p: np.min(np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(len(p)) * 9)  # noqa: E731
    assert d(pts[idx]) > d(pts[:50])
    m = init_model(pts, cols, max_points=100, opacity=0.1, max_sh_degree=3, random_rotation=True,
                   texture_mode="content_aware", fixed_res=16, seed=0)
    assert m.num_primitives == 100 and m.sh.shape == (100, 16, 3) and m.num_texels == 0
    assert torch.allclose(m.opacities, torch.full((100,), 0.1))
    sub = farthest_point_subsample(pts, 100, 0)
    assert torch.allclose(m.sh[:, 0] * 0.28209479177387814 + 0.5, torch.from_numpy(cols[sub]), atol=1e-6)
    assert torch.allclose(m.means, torch.from_numpy(pts[sub]))
    f = init_model(pts, cols, max_points=0, opacity=0.1, max_sh_degree=0, random_rotation=False,
                   texture_mode="fixed", fixed_res=16, seed=0)
    assert f.num_texels == 500 * 256 and bool((f.quats[:, 0] == 1).all())


def test_rotation_quaternion_round_trip_and_normal_frames():
    from ctgs.render.geometry import frames_from_normals, quat_to_rotmat, rotmat_to_quat

    g = torch.Generator().manual_seed(0)
    q = torch.randn(2000, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    q = q * torch.where(q[:, :1] < 0, -1.0, 1.0)
    q[:4] = torch.eye(4, dtype=torch.float64)  # identity and the three 180-degree turns (w = 0)
    back = rotmat_to_quat(quat_to_rotmat(q))
    assert torch.allclose(quat_to_rotmat(back), quat_to_rotmat(q), atol=1e-12)
    assert torch.allclose(back[4:], q[4:], atol=1e-12)
    n = torch.randn(500, 3, generator=g, dtype=torch.float64)
    n[0] = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    r = frames_from_normals(n, g)
    eye = torch.eye(3, dtype=torch.float64).expand(500, 3, 3)
    assert torch.allclose(r.transpose(1, 2) @ r, eye, atol=1e-12) and bool((torch.linalg.det(r) > 0).all())
    assert torch.allclose(r[:, :, 2], n / n.norm(dim=1, keepdim=True), atol=1e-12)


def test_init_normals_lie_in_the_local_plane():
    from ctgs.render.geometry import quat_to_rotmat
    from ctgs.train.start.init import pca_normals

    rng = np.random.default_rng(1)
    # Two planes: z = 0 (normal z) and x = 3 (normal x), with 1% thickness noise.
    a = np.c_[rng.uniform(-1, 1, (300, 2)), rng.normal(0, 0.01, 300)]
    b = np.c_[3 + rng.normal(0, 0.01, 300), rng.uniform(-1, 1, (300, 2))]
    pts = np.concatenate([a, b]).astype(np.float32)
    nrm = pca_normals(pts)
    assert np.median(np.abs(nrm[:300, 2])) > 0.99 and np.median(np.abs(nrm[300:, 0])) > 0.99
    m = init_model(pts, np.zeros_like(pts), max_points=0, opacity=0.1, max_sh_degree=0, random_rotation=True,
                   texture_mode="content_aware", fixed_res=16, seed=0, normals=True)
    z = quat_to_rotmat(m.quats.detach())[:, :, 2].numpy()
    assert np.median(np.abs(z[:300, 2])) > 0.99 and np.median(np.abs(z[300:, 0])) > 0.99


def test_mult4_allocation_pads_less_and_keeps_downscaled_sizes_even():
    m = model(means=[[0.0, 0.0, 3.0], [0.5, 0.0, 3.0]], scales=[[0.2, 0.2], [0.02, 0.21]], opacities=[0.9, 0.9],
              tex_res=[[0, 0]] * 2, textures=torch.zeros(0, 3), k_min=[0.002, 0.002])
    m.t2p_exp = torch.tensor([4, 3], dtype=torch.int32)  # texels 0.032 and 0.016
    # Active extents: 1.2 / 0.032 = 37.5 and (0.12, 1.26) / 0.016 = (7.5, 78.75) texels (+1 padding).
    assert texels.needed_res(m, 256, "pow2").tolist() == [[64, 64], [16, 128]]
    assert texels.needed_res(m, 256, "mult4").tolist() == [[40, 40], [12, 80]]
    # Every mult4 size halves to an even size, so re-centring after a downscale moves texels by whole texels.
    assert all(v % 4 == 0 for v in texels.needed_res(m, 256, "mult4").flatten().tolist())
    # texture_sigma bounds the allocated extent: +-2 sigma instead of +-3.
    assert texels.needed_res(m, 256, "mult4", sigma=2.0).tolist() == [[28, 28], [8, 56]]


def test_mult4_realloc_and_downscale_keep_the_image(tmp_path=None):
    m = model(means=[[0.0, 0.0, 3.0]], scales=[[0.2, 0.15]], opacities=[0.9], tex_res=[[0, 0]],
              textures=torch.zeros(0, 3), k_min=[0.004])
    opt = optimiser(m)
    texels.start_textures(m, opt, start_texels=8, min_exp=1, cap=256, mode="mult4")
    assert all(v % 4 == 0 for v in m.tex_res[0].tolist())
    # A smooth texture (passes E_d) downscales, then re-allocates (mult4) with its content still centred.
    ru, rv = m.tex_res[0].tolist()
    u = torch.linspace(-1, 1, ru)[None, :].expand(rv, ru)
    with torch.no_grad():
        act = (0.3 * u)[..., None].expand(rv, ru, 3).reshape(-1, 3)
        m.textures_raw.copy_(torch.logit((act + 1) / 2))
    before = image(m)
    down, _ = texels.downscale(m, opt, torch.ones(1, dtype=torch.bool), tau_ds=0.05)
    assert bool(down[0]) and m.tex_res[0].tolist() == [ru // 2, rv // 2]
    texels.realloc(m, opt, 256, "mult4")
    assert all(v % 4 == 0 or v == 2 for v in m.tex_res[0].tolist())
    assert torch.abs(image(m) - before).max() < 0.03  # a linear ramp survives x2 downsampling


def test_split_children_leave_the_candidates_unless_they_stay():
    """The authors' code zeroes the error of the primitives a split adds, so a routine does not upscale them:
    children_stay=False returns them as non-candidates; True (the CPU presets) carries the parent's flag. Either way a
    child of the x split is still a candidate for the y split."""
    means = [[x, 0.0, 3.0] for x in np.linspace(-1, 1, 4)]

    def fresh():
        m = model(means=means, scales=[[0.3, 0.3]] * 4, opacities=[0.9] * 4, tex_res=[[2, 2]] * 4, k_min=[0.005] * 4)
        return m, optimiser(m)

    cand = torch.tensor([True, True, False, False])
    m, opt = fresh()
    n, kept = split(m, opt, cand, tau=4.0, children_stay=True)
    # Both axes split: 2 parents -> 4 children each, the 2 others untouched.
    assert n == 2 + 4 and m.num_primitives == 2 + 8
    assert int(kept.sum()) == 8
    m, opt = fresh()
    n2, left = split(m, opt, cand, tau=4.0, children_stay=False)
    assert n2 == n and m.num_primitives == 2 + 8
    assert not left.any()
    # The untouched primitives keep their flags.
    m, opt = fresh()
    _, mixed = split(m, opt, torch.tensor([True, False, True, False]), tau=1e9, children_stay=False)
    assert mixed.tolist() == [True, False, True, False]


def test_active_texels_count_the_textures_as_the_authors_save_them():
    """The authors' save crops each texture tight to its active extent: e = ceil(active extent / texel size) per axis,
    e + 2 texels if e is even, e + 1 if odd (centred texels covering e), at most 256. num_texels counts the
    allocation."""
    from ctgs.model.extent import active_resolution, active_texels

    m = model(means=[[0.0, 0.0, 3.0], [0.5, 0.0, 3.0]], scales=[[0.2, 0.1], [0.05, 0.05]], opacities=[0.9, 0.9],
              tex_res=[[16, 16], [8, 8]], k_min=[0.05, 0.05], t2p_exp=[1, 1])
    e = torch.ceil(active_resolution(m)).long()
    assert e.tolist() in ([[12, 6], [3, 3]], [[13, 7], [4, 4]])  # 2 x 3 sigma x scale / 0.1 (float rounding)
    tight = {12: 14, 6: 8, 3: 4, 13: 14, 7: 8, 4: 6}
    expect = sum(tight[a] * tight[b] for a, b in e.tolist())
    assert m.num_texels == 16 * 16 + 8 * 8
    assert active_texels(m) == expect
    wide = model(means=[[0.0, 0.0, 3.0]], scales=[[50.0, 0.1]], opacities=[0.9], tex_res=[[256, 8]], k_min=[0.05],
                 t2p_exp=[1])
    assert active_texels(wide) == 256 * 8  # at most 256 on an axis


def test_thin_textures_downscale_only_with_the_authors_rule():
    """A texture 2 texels wide on one axis and wider on the other: the authors' code downscales it (any axis above
    2), downscale_thin=False (the CPU presets) leaves it; the routine's realloc then pads the thin axis again."""
    def fresh():
        m = model(means=[[0.0, 0.0, 3.0]], scales=[[0.4, 0.02]], opacities=[0.9], tex_res=[[8, 2]],
                  textures=torch.zeros(16, 3), k_min=[0.01], t2p_exp=[2])
        return m, optimiser(m)

    m, opt = fresh()
    down, e_d = texels.downscale(m, opt, torch.ones(1, dtype=torch.bool), tau_ds=0.02, thin=False)
    assert not down.any() and torch.isnan(e_d).all() and m.tex_res.tolist() == [[8, 2]]
    m, opt = fresh()
    down, e_d = texels.downscale(m, opt, torch.ones(1, dtype=torch.bool), tau_ds=0.02, thin=True)
    assert down.tolist() == [True] and float(e_d[0]) < 0.02  # a flat texture survives the round trip
    assert m.tex_res.tolist() == [[4, 1]] and m.t2p_exp.tolist() == [3] and m.num_texels == 4
    texels.realloc(m, opt, 256)
    assert int(m.tex_res.min()) >= 2


def test_texture_start_rounds_the_exponent_up_with_the_authors_rule():
    """The authors' code takes the texel size's exponent with ceil (at most start_texels across the smaller active
    extent); start_exp_ceil=False (the CPU presets) takes the nearest power of two."""
    def fresh():
        return model(means=[[0.0, 0.0, 3.0], [0.5, 0.0, 3.0], [0, 0.3, 3.0]],
                     scales=[[0.2, 0.2], [0.003, 0.003], [0.2, 0.1]], opacities=[0.9] * 3, tex_res=[[0, 0]] * 3,
                     textures=torch.zeros(0, 3), k_min=[0.002] * 3)

    m = fresh()
    texels.start_textures(m, optimiser(m), start_texels=8, min_exp=1, cap=256, ceil=True)
    # 2^6.23 -> 2^7 and 2^5.23 -> 2^6 (the nearest would be 6 and 5); prim 1 stays at the minimum.
    assert m.t2p_exp.tolist() == [7, 1, 6]
    extent = 2 * texels.active_half_extent(m).min(1).values
    across = (extent / texels.texel_size(m))[[0, 2]]
    assert bool(((across > 4) & (across <= 8)).all())


def _split_pair():
    """Two primitives 18 texels wide (tau 4 splits them on both axes), textures 16 x 16, Adam moments all 1."""
    m = model(means=[[-0.5, 0.0, 3.0], [0.5, 0.0, 3.0]], scales=[[0.03, 0.03]] * 2, opacities=[0.9] * 2,
              tex_res=[[16, 16]] * 2, k_min=[0.005] * 2)
    opt = optimiser(m)
    for st in (opt.exp_avg, opt.exp_avg_sq):
        for k in st:
            st[k] = torch.ones_like(st[k])
    return m, opt


def test_split_children_start_with_zero_moments_with_the_authors_rule():
    """The authors' code appends a split's children as new parameters (zero Adam moments, textures too) and drops
    the parent; split_fresh_moments=False (the CPU presets) lets them inherit the parent's. The primitive left
    alone keeps its moments either way."""
    from ctgs.model.surfels import jagged_offsets

    for fresh in (True, False):
        m, opt = _split_pair()
        kids = []
        split(m, opt, torch.tensor([True, False]), tau=4.0, fresh_children=fresh, children_out=kids)
        child = kids[0]
        assert m.num_primitives == 1 + 4 and child.tolist() == [False, True, True, True, True]
        for st in (opt.exp_avg, opt.exp_avg_sq):
            assert bool((st["means"][~child] == 1).all())
            assert bool((st["means"][child] == (0 if fresh else 1)).all())
            off, res = jagged_offsets(m.tex_res), m.tex_res.long()
            alone = st["textures_raw"][int(off[0]): int(off[0]) + int(res[0].prod())]
            assert alone.numel() > 0 and bool((alone == 1).all())
            kids_texels = st["textures_raw"][int(off[1]):]
            if fresh:
                assert kids_texels.numel() > 0 and bool((kids_texels == 0).all())
            else:  # the parent's, shifted (texels shifted in from outside its texture start at 0)
                assert float(kids_texels.mean()) > 0.5


def test_split_children_scale_is_capped_at_tau_texels_over_3_with_the_authors_rule():
    """A primitive far wider than tau texels: halving leaves its children wider than tau texels; the authors' code
    caps a child's scale on the split axis at tau x texel / 3."""
    def fresh():
        m = model(means=[[0.0, 0.0, 3.0]], scales=[[2.0, 0.005]], opacities=[0.9], tex_res=[[4, 4]], k_min=[0.005])
        return m, optimiser(m)

    tau = 4.0
    m, opt = fresh()
    k = float(texels.texel_size(m)[0])
    split(m, opt, torch.tensor([True]), tau=tau, scale_cap=False)
    assert torch.allclose(m.scales[:, 0], torch.full((2,), 1.0))
    m, opt = fresh()
    split(m, opt, torch.tensor([True]), tau=tau, scale_cap=True)
    assert m.num_primitives == 2
    assert torch.allclose(m.scales[:, 0], torch.full((2,), tau * k / 3), rtol=1e-5)
    assert torch.allclose(m.scales[:, 1], torch.full((2,), 0.005), rtol=1e-5)  # the other axis: untouched


def test_the_upscale_set_after_the_split_takes_the_top_fraction_of_every_primitive():
    """The authors' code upscales E above its (1 - top_fraction) quantile over every primitive after the split, E
    taken as 0 for the split's children and where the texel size is at its smallest: 10% of 20 primitives is 2, the
    largest E among those that can be upscaled, whatever a child or a minimum-size texel held."""
    from types import SimpleNamespace

    from ctgs.train.routines.passes import upscale_after_split

    n = 20
    m = model(means=[[0.1 * i, 0.0, 3.0] for i in range(n)], scales=[[0.05, 0.05]] * n, opacities=[0.9] * n,
              tex_res=[[4, 4]] * n, t2p_exp=[2] * n)
    m.t2p_exp[0] = 1  # at min_t2p_exp: cannot be upscaled
    E = torch.arange(1, n + 1, dtype=torch.float32).flip(0)  # E[0] = 20 (largest) ... E[19] = 1
    children = torch.zeros(n, dtype=torch.bool)
    children[1] = True  # E 19, a child of this split
    cfg = SimpleNamespace(upscale_split_children=False, min_t2p_exp=1, top_fraction=0.1)
    up = upscale_after_split(m, E, children, cfg, None)
    assert torch.nonzero(up).flatten().tolist() == [2, 3]
    cfg.upscale_split_children = True
    assert torch.nonzero(upscale_after_split(m, E, children, cfg, None)).flatten().tolist() == [1, 2]
    far = torch.zeros(n, dtype=torch.bool)
    far[2] = True
    cfg.upscale_split_children = False
    assert torch.nonzero(upscale_after_split(m, E, children, cfg, far)).flatten().tolist() == [3, 4]


def test_resized_textures_restart_their_moments_only_with_the_authors_rule():
    """The authors' code zeroes the Adam moments of every texture it upscales, downscales or re-sizes; with
    fresh_moments=False (the CPU presets) they are resampled with it. A texture left as it is keeps its moments."""
    from ctgs.model.surfels import jagged_offsets

    def fresh():
        m = model(means=[[-0.3, 0.0, 3.0], [0.3, 0.0, 3.0]], scales=[[0.05, 0.05]] * 2, opacities=[0.9] * 2,
                  tex_res=[[16, 16]] * 2, textures=torch.zeros(512, 3), t2p_exp=[2, 2], k_min=[0.005] * 2)
        opt = optimiser(m)
        for st in (opt.exp_avg, opt.exp_avg_sq):
            st["textures_raw"] = torch.ones_like(st["textures_raw"])
        return m, opt

    def moments(m, opt, i):
        off, n = int(jagged_offsets(m.tex_res)[i]), int(m.tex_res[i].long().prod())
        return [st["textures_raw"][off: off + n] for st in (opt.exp_avg, opt.exp_avg_sq)]

    first = torch.tensor([True, False])
    for fresh_moments in (True, False):
        for edit_texture in ("upscale", "downscale"):
            m, opt = fresh()
            if edit_texture == "upscale":
                done = texels.upscale(m, opt, first, 1, fresh_moments=fresh_moments)
            else:
                done, _ = texels.downscale(m, opt, first, tau_ds=1.0, fresh_moments=fresh_moments)
            assert done.tolist() == [True, False] and m.tex_res[0].tolist() != [16, 16]
            for mom in moments(m, opt, 0):
                assert bool((mom == (0 if fresh_moments else 1)).all())
            for mom in moments(m, opt, 1):
                assert bool((mom == 1).all())
        m, opt = fresh()
        with torch.no_grad():
            m.log_scales[0] += 1.0  # the first grows: its needed size changes; the second's does not
        need = texels.needed_res(m, 256)
        assert need[0].tolist() != [16, 16] and need[1].tolist() == [16, 16]
        texels.realloc(m, opt, 256, fresh_moments=fresh_moments)
        assert bool((moments(m, opt, 0)[0] == 0).all()) == fresh_moments
        assert bool((moments(m, opt, 1)[0] == 1).all())


def test_the_downscale_round_trip_with_corner_aligned_resampling_and_the_split_offset_truncated():
    """The authors' code resamples the downscale round trip with align_corners=True (a linear ramp's corner texels
    stay put, so E_d differs from the centre-keeping round trip) and truncates the split offset to whole texels."""
    def fresh():
        m = model(means=[[0.0, 0.0, 3.0]], scales=[[0.2, 0.2]], opacities=[0.9], tex_res=[[8, 8]],
                  textures=torch.zeros(64, 3), k_min=[0.01], t2p_exp=[2])
        u = torch.linspace(-0.6, 0.6, 8)
        with torch.no_grad():
            m.textures_raw.copy_(torch.logit(((u[None, :].expand(8, 8) + 1) / 2)).reshape(-1, 1).expand(64, 3))
        return m, optimiser(m)

    m, opt = fresh()
    _, e_centres = texels.downscale(m, opt, torch.ones(1, dtype=torch.bool), tau_ds=-1.0)
    m, opt = fresh()
    _, e_corners = texels.downscale(m, opt, torch.ones(1, dtype=torch.bool), tau_ds=-1.0, corners=True)
    assert float(e_corners[0]) != pytest.approx(float(e_centres[0]), rel=0.05)
    # offset: active extent 2 x 3 x 0.03 = 0.18 world units / 6 = 0.03 = 1.5 texels of 0.02 -> 2 rounded, 1 truncated
    for truncate, texels_off in ((False, 2), (True, 1)):
        s = model(means=[[0.0, 0.0, 3.0]], scales=[[0.03, 0.005]], opacities=[0.9], tex_res=[[16, 4]], k_min=[0.01],
                  t2p_exp=[1])
        split(s, optimiser(s), torch.tensor([True]), tau=4.0, truncate=truncate)
        assert s.num_primitives == 2
        assert torch.allclose(s.means[:, 0].abs(), torch.full((2,), 0.02 * texels_off), atol=1e-6)


def test_the_late_prune_removes_faint_primitives_and_updates_k_min():
    """Between the late downscales (the authors' every 250 iterations): prune below prune_opacity_late, new k_min."""
    from types import SimpleNamespace

    from ctgs.train.routines.passes import late_prune
    from train_helpers import camera

    m = model(means=[[0.0, 0.0, 3.0], [0.3, 0.0, 3.0]], scales=[[0.05, 0.05]] * 2, opacities=[0.9, 0.002],
              tex_res=[[4, 4]] * 2, k_min=[1.0, 1.0])
    stats = late_prune(m, optimiser(m), SimpleNamespace(prune_opacity_late=1.0 / 255.0), [camera()])
    assert stats == {"pruned": 1} and m.num_primitives == 1
    assert float(m.k_min[0]) < 0.1  # recomputed from the camera (3 units away, focal 60: 0.05 per pixel)
