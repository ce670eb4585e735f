"""error_image given as a function of the rendered rgb (ctgs.render.render): on the cpu backend one render
that lists its blended pairs; the statistics must equal a second render with that error image (cpu) and
the reference's, and the images must equal a plain render."""

from __future__ import annotations

import pytest
import torch
from scenes import cast, random_scene

import ctgs.render.api as api
from ctgs.render import render


def _error_fn(gt):
    return lambda rgb: (rgb.clamp(0, 1) - gt).abs().mean(-1) + 0.1


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_error_function_matches_two_renders_and_reference(dtype, monkeypatch):
    monkeypatch.setattr(api, "POISON_OUTPUTS", True)  # every output pixel must be written
    case = random_scene(60, seed=7, width=64, height=48, sh_degree=3, max_res=8)
    s, cam = cast(case.surfels, dtype), case.camera.to("cpu", dtype)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    gt = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    one = render(s, cam, backend="cpu", background=bg, error_image=_error_fn(gt))
    plain = render(s, cam, backend="cpu", background=bg)
    two = render(s, cam, backend="cpu", background=bg, error_image=_error_fn(gt)(plain.rgb))
    ref = render(s, cam, backend="reference", background=bg, error_image=_error_fn(gt))
    for name in ("rgb", "alpha", "depth"):
        assert torch.equal(getattr(one, name), getattr(plain, name)), name
    assert torch.equal(one.stats.count, two.stats.count) and torch.equal(one.stats.count, ref.stats.count)
    assert one.stats.count.sum() > 0
    # Sums over the same pairs in another order (per primitive here, per thread and tile in the kernel).
    tol = dict(atol=1e-12, rtol=1e-12) if dtype == torch.float64 else dict(atol=1e-5, rtol=1e-4)
    for name in ("contrib", "err"):
        torch.testing.assert_close(getattr(one.stats, name), getattr(two.stats, name), **tol)
        torch.testing.assert_close(getattr(one.stats, name), getattr(ref.stats, name), **(
            dict(atol=1e-9, rtol=0) if dtype == torch.float64 else dict(atol=1e-2, rtol=1e-4)))


def test_error_function_shape_is_checked():
    case = random_scene(10, seed=1, width=16, height=12)
    with pytest.raises(ValueError, match=r"error_image.*\[12, 16\]"):
        render(case.surfels, case.camera, backend="cpu", error_image=lambda rgb: rgb.mean(-1)[:-1])


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_backward_statistics_match_a_forward_with_the_error_image(dtype, threads):
    """A training render's backward given the error image of that render (BackwardStats) sums the same statistics as
    a forward with that error image, and leaves every gradient as a plain backward computes it, bit for bit."""
    from ctgs.render import BackwardStats

    case = random_scene(80, seed=3, width=64, height=48, sh_degree=1, max_res=8)
    s, cam = cast(case.surfels, dtype), case.camera.to("cpu", dtype)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    gt = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(2), dtype=dtype)
    names = ("means", "quats", "scales", "opacities", "sh", "textures")
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        grads = {}
        for with_stats in (False, True):
            leaves = {n: getattr(s, n).detach().clone().requires_grad_(True) for n in names}
            sg = type(s)(**{**vars(s), **leaves})
            sink = BackwardStats() if with_stats else None
            out = render(sg, cam, backend="cpu", background=bg, backward_stats=sink)
            if sink is not None:
                sink.error_image = _error_fn(gt)(out.rgb.detach())
            ((out.rgb - gt) ** 2).sum().backward()
            grads[with_stats] = {n: leaves[n].grad for n in names}
            if sink is not None:
                stats = sink
                e = sink.error_image
        forward = render(s, cam, backend="cpu", background=bg, error_image=e).stats
    finally:
        torch.set_num_threads(before)
    for n in names:
        assert torch.equal(grads[False][n], grads[True][n]), n
    assert forward.count.sum() > 0 and stats.contrib.shape == forward.contrib.shape
    # w from T recovered by division in the backward, from the running T in the forward: equal up to rounding
    tol = dict(atol=1e-10, rtol=1e-9) if dtype == torch.float64 else dict(atol=1e-4, rtol=1e-3)
    torch.testing.assert_close(stats.contrib, forward.contrib, **tol)
    torch.testing.assert_close(stats.err, forward.err, **tol)
    assert bool((stats.contrib[forward.count == 0] == 0).all())
