"""`ctgs export --bake-textures`: a textured surfel as one small splat per texel (ctgs.formats.bake), checked by rendering
it against the exact surfel and against the one-colour fold the plain exports make."""

from __future__ import annotations

import math

import pytest
import torch
from click.testing import CliRunner
from factory_io import random_model

from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.formats.bake import BAKE_SIGMA, bake_texels, plan_levels, split_opacity
from ctgs.formats.plain_ply import SH_C0, texture_means
from ctgs.metrics.psnr import psnr
from ctgs.render.geometry import rotmat_to_quat
from ctgs.model.surfels import SurfelModel, jagged_offsets
from ctgs.render import render
from ctgs.render.camera import Camera

CAM = Camera(fx=200.0, fy=200.0, cx=64.0, cy=64.0, width=128, height=128, viewmat=torch.eye(4))


def _surfel(res: int = 12, texel: float = 0.06, scale: float = 0.25, logit: float = 4.0, tilt_deg: float = 0.0,
            seed: int = 0) -> SurfelModel:
    """One textured surfel 3 units in front of CAM, a random texture (detail at the texel scale)."""
    g = torch.Generator().manual_seed(seed)
    th = math.radians(tilt_deg)
    rot = torch.tensor([[1.0, 0, 0], [0, math.cos(th), -math.sin(th)], [0, math.sin(th), math.cos(th)]])
    tex_res = torch.tensor([[res, res]], dtype=torch.int32)
    return SurfelModel(
        means=torch.tensor([[0.0, 0.0, 3.0]]), log_scales=torch.log(torch.tensor([[scale, scale]])),
        quats=rotmat_to_quat(rot[None]), opacity_logits=torch.tensor([logit]), sh=torch.zeros(1, 4, 3),
        textures_raw=torch.randn(res * res, 3, generator=g), k_min=torch.tensor([texel]),
        t2p_exp=torch.zeros(1, dtype=torch.int32), tex_res=tex_res, tex_offset=jagged_offsets(tex_res), sh_degree=1,
        texture_mode="content_aware")


def _folded(m: SurfelModel) -> SurfelModel:
    out = bake_texels(m, lattice_max_texel=0.0)  # every surfel one splat: the plain exports' fold
    return out


def _img(m: SurfelModel):
    return render(m.render_inputs(), CAM, backend="cpu")


@pytest.mark.parametrize("tilt", [0.0, 60.0])
def test_baked_surfel_renders_close_to_the_exact_one_and_far_closer_than_the_fold(tilt):
    m = _surfel(tilt_deg=tilt)
    exact, baked, folded = _img(m), _img(bake_texels(m)), _img(_folded(m))
    p_baked = float(psnr(baked.rgb.clamp(0, 1), exact.rgb.clamp(0, 1)))
    p_fold = float(psnr(folded.rgb.clamp(0, 1), exact.rgb.clamp(0, 1)))
    assert p_baked > 30.0 and p_baked > p_fold + 6.0, (p_baked, p_fold)
    assert abs(float(baked.alpha.sum()) / float(exact.alpha.sum()) - 1.0) < 0.05  # the surfel's coverage kept


def test_one_splat_per_texel_inside_the_surfel_with_the_texel_in_its_dc():
    m = _surfel(res=12, texel=0.06, scale=0.25)
    b = bake_texels(m)
    # The grid (12 x 12) and the rings out to the surfel's 3 sigma (0.75: 12.5 texels): the disc's texel count.
    assert abs(b.num_primitives / (math.pi * 12.5**2) - 1) < 0.05
    centre = (b.means[:, :2].norm(dim=1)).argmin()  # the splat nearest the surfel centre: a texel centre at +-k/2
    torch.testing.assert_close(b.means[centre, 2], torch.tensor(3.0))
    torch.testing.assert_close(b.scales[centre], torch.full((2,), BAKE_SIGMA * 0.06), rtol=1e-5, atol=0)
    iu, iv = [int(round(float(x) / 0.06 + 5.5)) for x in b.means[centre, :2]]
    texel = m.textures[iv * 12 + iu].double()
    torch.testing.assert_close(b.sh[centre, 0].double(), texel / SH_C0, rtol=0, atol=1e-5)
    torch.testing.assert_close(b.sh[:, 1:], torch.zeros_like(b.sh[:, 1:]))  # the bands as the surfel's (zero here)
    assert b.texture_mode == "none" and b.num_texels == 0 and b.sh_degree == 1


def test_coarse_texels_and_untextured_surfels_stay_one_folded_splat():
    coarse = _surfel(res=2, texel=0.8, scale=0.25)  # texels wider than the surfel: centres outside its 3 sigma
    b = bake_texels(coarse)
    assert b.num_primitives == 1
    torch.testing.assert_close(b.sh[0, 0].double(), coarse.sh[0, 0].double() + texture_means(coarse)[0] / SH_C0)
    plain = random_model(n=30, texture_mode="none")
    pb = bake_texels(plain)
    assert pb.num_primitives == 30
    torch.testing.assert_close(pb.means, plain.means)
    torch.testing.assert_close(_img(pb).rgb, _img(plain).rgb, atol=1e-5, rtol=0)


@pytest.mark.parametrize("target", [0.05, 0.5, 0.85, 0.98])
def test_split_opacity_composites_to_the_target_over_a_cell(target):
    """Against a dense, independent evaluation: a large uniform lattice at the solved peak opacity, its composite
    alpha averaged over a 20 x 20 grid of points of the central cell. Half-texel Gaussians reach at most 0.90 there
    (at the renderer's largest alpha, 0.99): a higher target gets that."""
    a = float(split_opacity(torch.tensor([target])))
    d = torch.arange(-6, 7, dtype=torch.float64)
    cu, cv = torch.meshgrid(d, d, indexing="ij")
    s = (torch.arange(20, dtype=torch.float64) + 0.5) / 20 - 0.5
    su, sv = torch.meshgrid(s, s, indexing="ij")
    rho = ((su.reshape(-1, 1) - cu.reshape(1, -1)) ** 2 + (sv.reshape(-1, 1) - cv.reshape(1, -1)) ** 2) / BAKE_SIGMA**2
    w = torch.exp(-0.5 * rho) * (rho <= 9.0)
    alpha = 1 - torch.prod(1 - a * w, dim=1)
    if target < 0.9:
        assert abs(float(alpha.mean()) - target) < 0.01
    else:
        assert a == pytest.approx(0.99) and 0.89 < float(alpha.mean()) < 0.91


def test_export_bakes_the_gaussian_formats_and_refuses_other_formats(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    m = random_model(n=20, sh_degree=1, seed=4)
    torch.save({"model": m.state_dict(), "scene_dir": str(tmp_path / "scene"), "images": "images", "holdout": 8,
                "iteration": 7, "config": {}}, run / "model.pt")
    n = bake_texels(m).num_primitives
    assert n > 20
    for fmt in ("ply", "splat", "spz", "compressed-ply", "sog", "glb-splats"):
        res = CliRunner().invoke(main, ["export", str(run), "--format", fmt, "--bake-textures"])
        assert res.exit_code == 0, res.output
        assert f"{n} " in res.output and "textures baked" in res.output
    res = CliRunner().invoke(main, ["export", str(run), "--format", "glb", "--bake-textures"])
    assert res.exit_code != 0
    assert "--bake-textures applies to --format ply, splat, spz, compressed-ply, sog, glb-splats" in res.output
    assert not (run / "model.glb").exists()


def _fields_equal(a: SurfelModel, b: SurfelModel) -> None:
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh", "tex_res", "tex_offset"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("chunk", [1, 37, 500])
def test_baking_a_chunk_at_a_time_gives_the_same_splats(chunk):
    m = random_model(n=40, sh_degree=2, seed=5)
    whole = bake_texels(m, chunk_splats=1 << 30)
    part = bake_texels(m, chunk_splats=chunk)  # 1: every surfel its own chunk; 37: many lattices split between
    assert whole.num_primitives > 40
    _fields_equal(whole, part)


def test_max_splats_refuses_before_baking_the_rest():
    m = random_model(n=40, sh_degree=1, seed=6)
    n = bake_texels(m).num_primitives
    assert bake_texels(m, max_splats=n).num_primitives == n
    with pytest.raises(UserError, match=f"more than {n - 1} splats .* export --format ply"):
        bake_texels(m, max_splats=n - 1, chunk_splats=64)


def _run(tmp_path, m: SurfelModel):
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"model": m.state_dict(), "scene_dir": str(tmp_path / "scene"), "images": "images", "holdout": 8,
                "iteration": 7, "config": {}}, run / "model.pt")
    return run


def test_spz_export_fits_the_readers_limit_and_says_so(tmp_path, monkeypatch):
    import ctgs.formats.spz

    m = random_model(n=20, sh_degree=1, seed=4)
    run = _run(tmp_path, m)
    assert bake_texels(m).num_primitives > 1000
    monkeypatch.setattr(ctgs.formats.spz, "MAX_POINTS", 1000)
    res = CliRunner().invoke(main, ["export", str(run), "--format", "spz", "--bake-textures"])
    assert res.exit_code == 0, res.output
    assert "fitted to 1000 splats" in res.output
    assert ctgs.formats.spz.read_spz(str(run / "model.spz")).num_primitives <= 1000


def test_bake_max_splats_needs_bake_textures_and_at_least_a_splat_per_surfel(tmp_path):
    run = _run(tmp_path, random_model(n=20, sh_degree=1, seed=4))
    res = CliRunner().invoke(main, ["export", str(run), "--format", "ply", "--bake-max-splats", "100"])
    assert res.exit_code != 0 and "--bake-max-splats applies with --bake-textures" in res.output
    res = CliRunner().invoke(main, ["export", str(run), "--format", "ply", "--bake-textures", "--bake-max-splats", "19"])
    assert res.exit_code != 0 and "20 surfels" in res.output and "at least 20" in res.output
    assert sorted(p.name for p in run.iterdir()) == ["model.pt"]


def _flat_and_detailed(n_each: int = 6) -> SurfelModel:
    """Two rows of identical surfels in front of CAM: the top row's textures flat (one colour), the bottom's random."""
    parts = []
    for row, flat in ((-0.45, True), (0.45, False)):
        for i in range(n_each):
            m = _surfel(res=16, texel=0.03, scale=0.12, seed=i)
            if flat:
                m.textures_raw = torch.full_like(m.textures_raw, 0.3 * (i % 3 - 1))
            m.means = torch.tensor([[(i - (n_each - 1) / 2) * 0.45, row, 3.0]])
            parts.append(m)
    cat = {name: torch.cat([getattr(p, name) for p in parts]) for name in
           ("means", "log_scales", "quats", "opacity_logits", "sh", "textures_raw", "k_min", "t2p_exp", "tex_res")}
    return SurfelModel(**cat, tex_offset=jagged_offsets(cat["tex_res"]), sh_degree=1, texture_mode="content_aware")


def test_a_budget_coarsens_the_flat_textures_first_and_beats_uniform_coarsening():
    m = _flat_and_detailed()
    flat, detailed = torch.arange(12) < 6, torch.arange(12) >= 6
    full = bake_texels(m)
    # A budget the full bake fits: the plan is the full bake.
    plan = plan_levels(m, full.num_primitives)
    assert plan["splats"] == plan["full_splats"] == full.num_primitives and bool((plan["level"] == 0).all())
    _fields_equal(bake_texels(m, budget=full.num_primitives), full)
    # 60% of it (the detailed half's splats and a few): flat textures give up theirs (no detail lost), the detailed
    # ones keep their texels.
    half = plan_levels(m, int(0.6 * full.num_primitives))
    assert half["splats"] <= int(0.6 * full.num_primitives)
    assert bool((half["level"][detailed] == 0).all()) and bool((half["level"][flat] != 0).all())
    assert bake_texels(m, levels=half["level"]).num_primitives == half["splats"]
    # One splat per surfel: everything folded, the plain exports' fold.
    _fields_equal(bake_texels(m, budget=12), _folded(m))
    # At the splat count of every surfel on 2x2 blocks, the plan draws the exact model closer than that uniform bake.
    exact = _img(m).rgb.clamp(0, 1)
    uniform = bake_texels(m, levels=torch.ones(12, dtype=torch.long))
    planned = bake_texels(m, budget=uniform.num_primitives)
    assert planned.num_primitives <= uniform.num_primitives
    p_uniform = float(psnr(_img(uniform).rgb.clamp(0, 1), exact))
    p_planned = float(psnr(_img(planned).rgb.clamp(0, 1), exact))
    assert p_planned > p_uniform + 1.0, (p_planned, p_uniform)  # observed +1.6 dB


def test_a_level_the_texture_grid_cannot_take_is_refused():
    m = _surfel(res=12)  # 12 = 4 x 3: blocks of 2 and 4 tile it, 8 does not
    bake_texels(m, levels=torch.tensor([2]))
    with pytest.raises(ValueError, match="level 3"):
        bake_texels(m, levels=torch.tensor([3]))
