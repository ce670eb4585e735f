"""k_min (analytic), E (hand-computed), percentile selection, tau_tr schedule, routine calendar."""

from __future__ import annotations

import math

import pytest

import torch

from ctgs.metrics.ssim import ssim, ssim_map
from ctgs.render.camera import Camera
from ctgs.train.config import schedule
from ctgs.train.config import TrainConfig
from ctgs.train.routines.error import accumulate_error, error_image, top_fraction_mask
from ctgs.train.routines.kmin import compute_k_min


def _cam(tz: float, f: float) -> Camera:
    vm = torch.eye(4)
    vm[2, 3] = tz  # camera at world z = -tz looking down +z
    return Camera(fx=f, fy=f, cx=50, cy=40, width=100, height=80, viewmat=vm)


def test_k_min_closest_camera_and_unseen():
    means = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, 1.0], [100.0, 0.0, 5.0]])
    cams = [_cam(0.0, 100.0), _cam(3.0, 50.0)]  # second camera: depth 8 (point 0) and 4 (point 1)
    k = compute_k_min(means, cams)
    # point 0: min(5/100, 8/50) = 0.05; point 1: min(1/100, 4/50) = 0.01; point 2 unseen: the largest seen.
    assert torch.allclose(k, torch.tensor([0.05, 0.01, 0.05]))
    behind = compute_k_min(torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0]]), [_cam(0.0, 100.0)])
    assert torch.allclose(behind, torch.tensor([0.02, 0.02]))


def test_E_hand_computed():
    # Two views (HW = 4 and 2), two primitives.
    v1 = (torch.tensor([0.4, 0.0]), torch.tensor([2.0, 0.0]), 4)
    v2 = (torch.tensor([0.1, 0.3]), torch.tensor([1.0, 1.0]), 2)
    e = accumulate_error([v1, v2])
    # prim 0: num = (0.4/4)(2/4) + (0.1/2)(1/2) = 0.05 + 0.025; den = 0.5 + 0.5 -> 0.075
    # prim 1: num = 0 + (0.3/2)(1/2) = 0.075; den = 0.5 -> 0.15
    assert torch.allclose(e, torch.tensor([0.075, 0.15]))
    assert accumulate_error([(torch.zeros(1), torch.zeros(1), 4)]).tolist() == [0.0]


def test_error_image_formula():
    a = torch.rand(20, 24, 3, generator=torch.Generator().manual_seed(0))
    b = torch.rand(20, 24, 3, generator=torch.Generator().manual_seed(1))
    e = error_image(a, b, 0.2)
    expect = 0.8 * (a - b).abs().mean(-1) + 0.2 * (1 - ssim_map(a, b)).mean(-1)
    assert e.shape == (20, 24) and torch.allclose(e, expect)
    assert float(error_image(a, a).abs().max()) < 1e-5


def test_ssim_properties():
    a = torch.rand(32, 40, 3, generator=torch.Generator().manual_seed(0))
    assert abs(float(ssim(a, a)) - 1) < 1e-5
    b = (a + 0.2 * torch.randn(a.shape, generator=torch.Generator().manual_seed(2))).clamp(0, 1)
    assert float(ssim(a, b)) < 0.9
    # Matches skimage (Gaussian 11x11, sigma 1.5) away from the border, where padding conventions differ.
    from skimage.metrics import structural_similarity

    _, full = structural_similarity(a.numpy(), b.numpy(), channel_axis=2, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False, data_range=1.0, full=True)
    ours = ssim_map(a, b).numpy()
    assert abs(ours[6:-6, 6:-6] - full[6:-6, 6:-6]).max() < 1e-4
    x = a.clone().requires_grad_(True)
    ssim(x, b).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_top_fraction_is_the_top_ten_percent():
    e = torch.randperm(1000).float() + 1
    m = top_fraction_mask(e, 0.1)
    assert int(m.sum()) == 100 and float(e[m].min()) == 901.0
    # Never-seen primitives (E = 0) are never selected, even if they fill the top decile.
    z = torch.zeros(50)
    assert not top_fraction_mask(z, 0.1).any()


def test_tau_tr_schedule_and_calendar():
    c = TrainConfig()
    assert schedule.tau_tr(c, 0) == 64 and schedule.tau_tr(c, 3500) == 48 and schedule.tau_tr(c, 7000) == 32
    assert schedule.tau_tr(c, 20000) == 32
    assert schedule.routine_kind(c, 250) is None  # before texture start (500)
    assert schedule.routine_kind(c, 500) == "full" and schedule.routine_kind(c, 750) == "full"
    assert schedule.routine_kind(c, 760) is None
    assert schedule.routine_kind(c, 25000) == "full" and schedule.routine_kind(c, 25100) is None
    # after the routines: a light prune every 250 (the authors' code), a downscale every 1000, none at the end
    assert schedule.routine_kind(c, 25250) == "late_prune" and schedule.routine_kind(c, 25500) == "late_prune"
    assert schedule.routine_kind(c, 26000) == "late" and schedule.routine_kind(c, 30000) is None
    assert schedule.routine_kind(TrainConfig(late_prune_every=0), 25250) is None
    # A schedule is a fraction of the run: 3000 iterations = every paper count x 0.1.
    short = TrainConfig(iterations=3000)
    assert schedule.texture_start(short) == 50 and schedule.routine_kind(short, 25) is None
    assert schedule.routine_kind(short, 50) == "full" and schedule.routine_kind(short, 75) == "full"
    assert schedule.routine_kind(short, 2500) == "full" and schedule.routine_kind(short, 2510) is None
    assert schedule.routine_kind(short, 2525) == "late_prune"
    assert schedule.routine_kind(short, 2600) == "late" and schedule.routine_kind(short, 3000) is None
    assert schedule.sh_degree(short, 99) == 0 and schedule.sh_degree(short, 100) == 1
    assert schedule.tau_tr(short, 350) == 48
    # schedule_scale > 0 overrides the fraction: paper counts x 1 on a 10k run ends routines at 10000 - 3000.
    pinned = TrainConfig(iterations=10000, schedule_scale=1.0)
    assert schedule.routine_kind(pinned, 7000) == "full" and schedule.routine_kind(pinned, 7250) == "late_prune"
    # Non-integer periods fire once per multiple (250 x 0.12 = 30 within float rounding).
    odd = TrainConfig(iterations=3600)
    assert [i for i in range(1, 200) if schedule.every(odd, 250, i)] == [30, 60, 90, 120, 150, 180]
    frac = TrainConfig(iterations=1000)  # period 8.33: fires at 9, 17, 25, ...
    assert [i for i in range(1, 30) if schedule.every(frac, 250, i)] == [9, 17, 25]
    assert schedule.sh_degree(c, 999) == 0 and schedule.sh_degree(c, 3000) == 3 and schedule.sh_degree(c, 9000) == 3
    assert schedule.position_lr(c, 0, 2.0) == 1.6e-4 * 2 and math.isclose(schedule.position_lr(c, 30000, 1.0), 1.6e-6)
    lrs = schedule.learning_rates(c, 499, 1.0, 16, "cpu")
    assert lrs["textures_raw"] == 0.0 and schedule.learning_rates(c, 500, 1.0, 16, "cpu")["textures_raw"] == 7e-4
    assert lrs["sh"][0, 0, 0] == 2.5e-3 and lrs["sh"][0, 1, 0] == 1.25e-4


def test_texture_lr_constant_by_default_and_exponential_decay_when_asked():
    c = TrainConfig()
    assert schedule.texture_lr(c, 499) == 0.0 and schedule.texture_lr(c, 500) == 7e-4 == schedule.texture_lr(c, 29999)
    d = TrainConfig(lr_texture=7e-3, lr_texture_final=7e-4)
    assert schedule.texture_lr(d, 499) == 0.0 and math.isclose(schedule.texture_lr(d, 500), 7e-3)
    assert math.isclose(schedule.texture_lr(d, 30000), 7e-4, rel_tol=1e-9)
    mid = (500 + 30000) // 2  # geometric mean half way (exponential decay)
    assert math.isclose(schedule.texture_lr(d, mid), math.sqrt(7e-3 * 7e-4), rel_tol=1e-3)
    assert schedule.texture_lr(TrainConfig(method="2dgs"), 5000) == 0.0
    assert schedule.learning_rates(d, 500, 1.0, 16, "cpu")["textures_raw"] == schedule.texture_lr(d, 500)


def test_scale_lr_constant_by_default_and_exponential_decay_when_asked():
    c = TrainConfig()
    assert schedule.scale_lr(c, 0) == 0.005 == schedule.scale_lr(c, 29999)
    assert schedule.learning_rates(c, 10, 1.0, 16, "cpu")["log_scales"] == 0.005
    d = TrainConfig(iterations=1500, lr_scale=0.015, lr_scale_final=0.005)
    assert math.isclose(schedule.scale_lr(d, 0), 0.015) and math.isclose(schedule.scale_lr(d, 1500), 0.005)
    assert math.isclose(schedule.scale_lr(d, 750), math.sqrt(0.015 * 0.005), rel_tol=1e-9)
    assert schedule.scale_lr(d, 100) > schedule.scale_lr(d, 1000) > schedule.scale_lr(d, 1499)
    assert schedule.learning_rates(d, 750, 1.0, 16, "cpu")["log_scales"] == schedule.scale_lr(d, 750)


def test_content_opacity_reset_follows_a_full_routine_up_to_densify_until():
    # Off by default (the paper has no reset in content-aware runs).
    fast = TrainConfig(iterations=3000, routine_every=1000, opacity_reset_every=7500)
    assert not any(schedule.content_opacity_reset(fast, i) for i in range(1, 3000))
    # fast's calendar: full routines every 100 from 100 to 2500, resets every 750 up to 1500: the reset due at 750
    # waits for the routine at 800, the one at 1500 falls on a routine, 2250 is past densify_until.
    on = TrainConfig(iterations=3000, routine_every=1000, opacity_reset_every=7500, content_opacity_reset=True)
    assert [i for i in range(1, 3000) if schedule.content_opacity_reset(on, i)] == [800, 1500]
    # balanced: routines every 166.7 iterations (fired at 167, 334, ...), resets at 2500 and 5000, both routines.
    bal = TrainConfig(iterations=10000, routine_every=500, opacity_reset_every=7500, content_opacity_reset=True)
    assert [i for i in range(1, 10000) if schedule.content_opacity_reset(bal, i)] == [2500, 5000]
    # Never in a baseline run (they have their own 3DGS reset) nor between routines.
    baseline = TrainConfig(iterations=3000, method="2dgs", content_opacity_reset=True)
    assert not any(schedule.content_opacity_reset(baseline, i) for i in range(1, 3000))
    # A re-planned run's shifted calendar: still once per reset period, at a full routine.
    shifted = [i for i in range(1, 3000) if schedule.content_opacity_reset(on, i, shift=37.0)]
    assert len(shifted) == 2 and all(schedule.routine_kind(on, i, 37.0) == "full" for i in shifted)


def test_densifications_keep_their_spacing_in_a_short_run():
    """However short the run, densifications are densify_min_steps steps apart (the paper's 100) and the opacity resets
    keep their ratio to them; at 30k, and where the scaled period is already longer, the calendar is the paper's."""
    paper = TrainConfig(method="2dgs")
    assert schedule.densify_stretch(paper) == 1.0
    assert [i for i in range(1, 1000) if schedule.densify_active(paper, i)] == [600, 700, 800, 900]
    assert [i for i in range(1, 10000) if schedule.opacity_reset(paper, i)] == [3000, 6000, 9000]
    # 1,055 planned steps (a 10-minute budget): scaled alone, densify every 3.5 steps from 18 to 527 (145 of them)
    short = TrainConfig(method="2dgs", iterations=1055)
    bare = TrainConfig(method="2dgs", iterations=1055, densify_min_steps=0)
    assert sum(schedule.densify_active(bare, i) for i in range(1, 1056)) == 145
    fired = [i for i in range(1, 1056) if schedule.densify_active(short, i)]
    assert fired == [100, 200, 300, 400, 500] and schedule.densify_stretch(short) == pytest.approx(100 / 3.5166, 1e-3)
    assert [i for i in range(1, 1056) if schedule.opacity_reset(short, i)] == []  # 30 densifications apart: none
    # `fast`'s baseline (densify every 2500 paper-scale) at 3000 steps: 250 apart, unchanged
    fast = TrainConfig(method="2dgs", iterations=3000, densify_every=2500, opacity_reset_every=7500)
    assert schedule.densify_stretch(fast) == 1.0 and [i for i in range(1, 3001) if schedule.opacity_reset(fast, i)] == [750, 1500]
