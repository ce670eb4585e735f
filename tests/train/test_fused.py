"""The fused CPU kernels of the training loop (ctgs.ops.fused, kernels/cpu/dense.cpp) against the PyTorch
expressions they replace: Adam (scalar and per-element learning rates, the non-finite count), the
texel L1 regulariser (value, gradient, gradcheck) and the photometric loss (kernels/cpu/ssim.cpp: value,
gradient, error image, gradcheck, threads), in float32 and float64."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from ctgs.ops import fused
from ctgs.train.step.adam import BETA1, BETA2, SurfelAdam
from ctgs.train.step.loss import photometric_loss

@pytest.fixture(autouse=True, scope="module")
def _cpu_extension():
    """The ops (torch.ops.ctgs) exist once the CPU extension is loaded."""
    assert fused.cpu_ext() is not None


# One fused pass vs PyTorch's chain of ops: the same formula, rounded in a different order.
ADAM_ATOL = {torch.float32: 1e-6, torch.float64: 1e-14}


def _torch_adam(p, g, m, v, lr, t, eps):
    m.mul_(BETA1).add_(g, alpha=1 - BETA1)
    v.mul_(BETA2).addcmul_(g, g, value=1 - BETA2)
    denom = (v / (1 - BETA2 ** t)).sqrt_().add_(eps)
    p.sub_(lr * (m / (1 - BETA1 ** t)) / denom)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("per_element_lr", [False, True])
def test_adam_step_matches_pytorch(dtype, per_element_lr):
    gen = torch.Generator().manual_seed(1)
    shape = (1037, 4, 3)  # not a multiple of the kernel's chunk or lane width
    p, g = torch.randn(shape, generator=gen, dtype=dtype), torch.randn(shape, generator=gen, dtype=dtype)
    m = torch.randn(shape, generator=gen, dtype=dtype) * 0.1
    v = torch.rand(shape, generator=gen, dtype=dtype) * 0.01
    lr = torch.tensor([1e-2, 1e-3, 1e-3, 1e-3], dtype=dtype).view(1, 4, 1) if per_element_lr else 3e-3
    ref = [x.clone() for x in (p, m, v)]
    for t in (1, 7):
        _torch_adam(*ref[:1], g, *ref[1:], lr, t, 1e-15)
        lr_t = lr.expand_as(p).contiguous() if per_element_lr else None
        bad = torch.ops.ctgs.adam_step(p, g, m, v, lr_t, 0.0 if per_element_lr else lr, BETA1, BETA2, t,
                                            1e-15, 2)
        assert bad == 0
        for x, y in zip((p, m, v), ref):
            torch.testing.assert_close(x, y, atol=ADAM_ATOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_fused_adam_step_matches_pytorch(dtype):
    """The GPU's Adam step (ctgs.train.step.adam.torch_fused_step: torch's fused kernel, run here on CPU tensors) is
    the same update as the PyTorch lines; a tensor lr (SH bands) is left to them."""
    from ctgs.train.step.adam import torch_fused_step

    gen = torch.Generator().manual_seed(2)
    shape = (2049, 3)
    p, g = torch.randn(shape, generator=gen, dtype=dtype), torch.randn(shape, generator=gen, dtype=dtype)
    m = torch.randn(shape, generator=gen, dtype=dtype) * 0.1
    v = torch.rand(shape, generator=gen, dtype=dtype) * 0.01
    ref = [x.clone() for x in (p, m, v)]
    for t in (1, 7, 3000):
        _torch_adam(*ref[:1], g, *ref[1:], 7e-4, t, 1e-15)
        assert torch_fused_step(p, g, m, v, 7e-4, t, 1e-15)
        for x, y in zip((p, m, v), ref):
            torch.testing.assert_close(x, y, atol=ADAM_ATOL[dtype], rtol=0)
    assert not torch_fused_step(p, g, m, v, torch.tensor(1e-3, dtype=dtype), 1, 1e-15)
    assert not torch_fused_step(p, g.to(torch.float64 if dtype == torch.float32 else torch.float32), m, v, 1e-3, 1,
                                1e-15)


def test_adam_counts_non_finite_results():
    p = torch.zeros(100)
    g = torch.ones(100)
    g[3], g[50] = float("nan"), float("inf")
    m, v = torch.zeros(100), torch.zeros(100)
    assert torch.ops.ctgs.adam_step(p, g, m, v, None, 1e-3, BETA1, BETA2, 1, 1e-15, 1) == 2
    p, g = torch.ones(10), torch.ones(10)
    assert torch.ops.ctgs.adam_step(p, g, torch.zeros(10), torch.zeros(10), None, 1e39, BETA1, BETA2, 1,
                                         1e-15, 1) == 10  # an lr that overflows float32


def test_surfel_adam_reports_the_parameter_made_non_finite():
    names = ("means", "log_scales", "quats", "opacity_logits", "sh", "textures_raw")
    model = SimpleNamespace(**{n: torch.zeros(5, 3, requires_grad=True) for n in names})
    opt = SurfelAdam(model)
    for n in names:
        getattr(model, n).grad = torch.ones(5, 3)
    model.quats.grad[2, 1] = float("nan")
    opt.step(model, {n: 1e-3 for n in names})
    assert opt.nonfinite == ["quats"] and opt.unchecked == []


def _jagged(dtype, seed=0):
    res = torch.tensor([[4, 4], [0, 0], [3, 5], [2, 2], [8, 8], [1, 3]], dtype=torch.int32)
    sizes = res[:, 0].long() * res[:, 1].long()
    off = torch.cumsum(sizes, 0) - sizes
    raw = torch.randn(int(sizes.sum()), 3, generator=torch.Generator().manual_seed(seed), dtype=dtype) * 3
    raw[0, 0] = 0.0  # sign(0): no gradient, like abs()
    # Per-primitive weights as the loss makes them: 0 (not rasterized), 1, and 1 - transmittance in between.
    weight = torch.tensor([1.0, 1.0, 0.0, 0.375, 1.0, 0.8], dtype=dtype)
    return SimpleNamespace(textures_raw=raw.requires_grad_(True), tex_offset=off, tex_res=res), weight, sizes


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_texel_l1_matches_pytorch(dtype):
    model, weight, sizes = _jagged(dtype)
    a = fused.texel_l1(model, weight)
    textures = 2.0 * torch.sigmoid(model.textures_raw) - 1.0
    b = (textures.abs().sum(1) * torch.repeat_interleave(weight, sizes)).sum()
    ga, = torch.autograd.grad(a * 0.7, model.textures_raw)
    gb, = torch.autograd.grad(b * 0.7, model.textures_raw)
    tol = 1e-5 if dtype == torch.float32 else 1e-13
    torch.testing.assert_close(a, b, atol=tol * float(b.detach()), rtol=0)
    torch.testing.assert_close(ga, gb, atol=tol, rtol=0)
    assert ga[int(sizes[:2].sum()):int(sizes[:3].sum())].abs().max() == 0  # the invisible primitive
    # A bool mask is the 0/1 weight.
    mask = weight > 0.5
    torch.testing.assert_close(fused.texel_l1(model, mask), fused.texel_l1(model, mask.to(dtype)), atol=0, rtol=0)
    with pytest.raises(ValueError, match="weight must be"):
        fused.texel_l1(model, weight[:-1])


def test_texel_l1_gradcheck_and_layout_check():
    model, weight, _ = _jagged(torch.float64, seed=2)
    f = lambda r: fused._TexelL1.apply(r, weight, model.tex_offset, model.tex_res)  # noqa: E731
    assert torch.autograd.gradcheck(f, (model.textures_raw,))
    with pytest.raises(RuntimeError, match="packed"):
        fused._TexelL1.apply(model.textures_raw, weight, model.tex_offset + 1, model.tex_res)
    with pytest.raises(RuntimeError, match="weight"):  # the kernel takes weights of raw's dtype only
        fused._TexelL1.apply(model.textures_raw, weight.float(), model.tex_offset, model.tex_res)


def test_jagged_remap_matches_pytorch(monkeypatch):
    """The compiled re-layout (split children with shifts, crops, pads, duplicates) equals the index
    arithmetic it replaces, for every buffer; so does replace_blocks built on it."""
    from ctgs.model import jagged
    from ctgs.model.surfels import jagged_offsets

    gen = torch.Generator().manual_seed(4)
    old_res = torch.tensor([[4, 4], [0, 0], [2, 8], [8, 2], [16, 16], [1, 1]], dtype=torch.int32)
    old_off = jagged_offsets(old_res)
    t = int(old_off[-1] + 1)
    bufs = [torch.randn(t, 3, generator=gen), torch.rand(t, 3, generator=gen)]
    src = torch.tensor([0, 2, 2, 3, 4, 4, 5, 1, 0])
    shift = torch.tensor([[0, 0], [1, 0], [-1, 3], [0, -2], [5, 0], [-9, 2], [0, 0], [0, 0], [2, 2]])
    new_res = torch.tensor([[8, 2], [2, 8], [4, 4], [2, 2], [16, 8], [4, 32], [2, 2], [2, 2], [1, 4]],
                           dtype=torch.int32)
    fast, off_fast = jagged.remap(bufs, old_res, old_off, src, shift, new_res)
    monkeypatch.setattr(jagged, "_cpu_remap", lambda *a: None)
    slow, off_slow = jagged.remap(bufs, old_res, old_off, src, shift, new_res)
    assert torch.equal(off_fast, off_slow)
    for a, b in zip(fast, slow):
        assert torch.equal(a, b)
    blocks = [(torch.tensor([0, 4]), [torch.randn(2, 2, 2, 3, generator=gen) for _ in bufs])]
    res2 = old_res.clone()
    res2[0] = res2[4] = torch.tensor([2, 2], dtype=torch.int32)
    slow2 = jagged.replace_blocks(bufs, old_res, old_off, res2, blocks)
    monkeypatch.undo()
    fast2 = jagged.replace_blocks(bufs, old_res, old_off, res2, blocks)
    assert torch.equal(fast2[1], slow2[1])
    for a, b in zip(fast2[0], slow2[0]):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_texel_activation_matches_pytorch(dtype):
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(1001, 3, generator=gen, dtype=dtype) * 4  # length not a multiple of the lane width
    x[0, :] = torch.tensor([0.0, 200.0, -200.0], dtype=dtype)  # saturation: exactly +-1, gradient 0
    x.requires_grad_(True)
    y = fused.texel_activation(x)
    ref = 2.0 * torch.sigmoid(x) - 1.0
    g = torch.randn(x.shape, generator=gen, dtype=dtype)
    gy, = torch.autograd.grad(y, x, g)
    gr, = torch.autograd.grad(ref, x, g)
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(y, ref, atol=tol, rtol=0)
    torch.testing.assert_close(gy, gr, atol=tol, rtol=0)
    assert y[0].tolist() == [0.0, 1.0, -1.0] and gy[0, 1:].abs().max() == 0
    if dtype == torch.float64:
        assert torch.autograd.gradcheck(fused.texel_activation, (x[1:50].detach().requires_grad_(True),))


def _torch_photometric(render, gt, lam):
    from ctgs.metrics.ssim import ssim_map

    l1 = (render - gt).abs().mean()
    s = ssim_map(render, gt).mean()
    return (1 - lam) * l1 + lam * (1 - s), l1, s


# Shapes: smaller than the 11-tap window in both directions, one channel, odd sizes, the demo's size.
PHOTO_SHAPES = [(1, 1, 1), (5, 7, 3), (37, 53, 3), (20, 30, 1), (144, 192, 3)]
PHOTO_RTOL = {torch.float32: 2e-5, torch.float64: 1e-12}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", PHOTO_SHAPES)
@pytest.mark.parametrize("lam", [0.0, 0.2, 1.0])
def test_photometric_loss_matches_pytorch(dtype, shape, lam):
    gen = torch.Generator().manual_seed(sum(shape))
    gt = torch.rand(shape, generator=gen, dtype=dtype)
    noise = 0.1 * torch.randn(shape, generator=gen, dtype=dtype)
    render = (gt + noise).clamp(0, 1)
    render[..., 0].view(-1)[::5] = gt[..., 0].view(-1)[::5]  # exact ties: |d| has gradient 0 there
    render.requires_grad_()
    assert fused.fusable(render.detach(), gt)
    total, l1, s = fused.photometric_loss(render, gt, lam)
    (g_fused,) = torch.autograd.grad(3.0 * total, render)  # an upstream gradient != 1
    ref_total, ref_l1, ref_s = _torch_photometric(render, gt, lam)
    (g_ref,) = torch.autograd.grad(3.0 * ref_total, render)
    rtol = PHOTO_RTOL[dtype]
    for a, b in ((total, ref_total), (l1, ref_l1), (s, ref_s)):
        torch.testing.assert_close(a.detach(), b.detach(), rtol=rtol, atol=rtol)
    assert not l1.requires_grad and not s.requires_grad
    scale = max(float(g_ref.abs().max()), 3.0 / render.numel())  # the L1 part alone: 3 (1 - lam) / numel
    torch.testing.assert_close(g_fused, g_ref, rtol=0, atol=rtol * scale)
    e = fused.error_image(render.detach(), gt, lam)
    from ctgs.metrics.ssim import ssim_map

    e_ref = (1 - lam) * (gt - render.detach()).abs().mean(-1) + lam * (1 - ssim_map(render.detach(), gt)).mean(-1)
    assert e.shape == shape[:2]
    torch.testing.assert_close(e, e_ref, rtol=0, atol=rtol)


def test_photometric_loss_gradcheck_and_threads():
    gen = torch.Generator().manual_seed(3)
    gt = torch.rand(9, 13, 3, generator=gen, dtype=torch.float64)
    # Away from render == gt, where |d| is not differentiable.
    render = (gt + 0.05 + 0.1 * torch.rand(9, 13, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda r: fused.photometric_loss(r, gt, 0.3)[0], (render,))
    # The row split over threads changes nothing (each row's sums are formed in the same order).
    x, y = torch.rand(61, 47, 3, generator=gen), torch.rand(61, 47, 3, generator=gen)
    outs = [torch.ops.ctgs.photometric_loss(x, y, 0.2, True, True, t) for t in (1, 2, 3)]
    for o in outs[1:]:
        for a, b in zip(o, outs[0]):
            assert torch.equal(a, b)


def test_photometric_loss_falls_back_off_the_fused_path():
    gen = torch.Generator().manual_seed(4)
    gt = torch.rand(12, 10, 3, generator=gen).requires_grad_()  # a gradient w.r.t. gt: PyTorch path
    render = torch.rand(12, 10, 3, generator=gen).requires_grad_()
    assert fused.photometric_loss(render, gt, 0.2) is None  # the compiled pass does not apply
    total, _, _ = photometric_loss(render, gt, 0.2)
    ref, _, _ = _torch_photometric(render, gt, 0.2)
    torch.testing.assert_close(total, ref)
    total.backward()
    assert gt.grad is not None
    with pytest.raises(ValueError, match="one shape"):
        photometric_loss(render, gt[:, :5], 0.2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_accumulate_pairs_matches_pytorch_index_add(dtype):
    # E's per-view statistics (ctgs/render/rasterize.py rasterize_error_fn): the same sums in the same order.
    gen = torch.Generator().manual_seed(6)
    P, n, hw = 20000, 301, 1200
    pix = torch.randint(0, hw, (P,), generator=gen, dtype=torch.int32)
    prim = torch.randint(0, n - 1, (P,), generator=gen, dtype=torch.int32)  # primitive n-1 never blended
    w, e = torch.rand(P, generator=gen, dtype=dtype), torch.rand(30, 40, generator=gen, dtype=dtype)
    count, contrib, err = torch.ops.ctgs.accumulate_pairs(pix, prim, w, e, n, 1)
    assert torch.equal(count, torch.bincount(prim, minlength=n).to(torch.int32))
    assert torch.equal(contrib, w.new_zeros(n).index_add_(0, prim, w))
    assert torch.equal(err, w.new_zeros(n).index_add_(0, prim, e.reshape(-1)[pix] * w))
    assert count[-1] == 0 and contrib[-1] == 0 and err[-1] == 0
    with pytest.raises(RuntimeError, match="out of range"):
        torch.ops.ctgs.accumulate_pairs(pix, prim, w, e[:2], n, 1)


@pytest.mark.parametrize("threads", [2, 3])
def test_accumulate_pairs_in_chunks_per_thread(threads):
    # More threads: each sums a contiguous chunk of the pairs in order, the chunks are added in order.
    gen = torch.Generator().manual_seed(7)
    P, n, hw = 200003, 501, 4000
    pix = torch.randint(0, hw, (P,), generator=gen, dtype=torch.int32)
    prim = torch.randint(0, n - 1, (P,), generator=gen, dtype=torch.int32)
    w, e = torch.rand(P, generator=gen, dtype=torch.float64), torch.rand(hw, generator=gen, dtype=torch.float64)
    count, contrib, err = torch.ops.ctgs.accumulate_pairs(pix, prim, w, e, n, threads)
    again = torch.ops.ctgs.accumulate_pairs(pix, prim, w, e, n, threads)
    assert all(torch.equal(a, b) for a, b in zip((count, contrib, err), again))  # deterministic
    assert torch.equal(count, torch.bincount(prim, minlength=n).to(torch.int32))
    torch.testing.assert_close(contrib, w.new_zeros(n).index_add_(0, prim, w), rtol=1e-13, atol=0)
    torch.testing.assert_close(err, w.new_zeros(n).index_add_(0, prim, e[pix] * w), rtol=1e-13, atol=0)
    bad = pix.clone()
    bad[P - 5] = hw
    with pytest.raises(RuntimeError, match=f"pair {P - 5} out of range"):
        torch.ops.ctgs.accumulate_pairs(bad, prim, w, e, n, threads)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_texel_l1_on_activated_textures_matches_the_raw_form(dtype):
    # The trainer passes the render's activated offsets: the same term and the same gradient w.r.t. raw.
    from ctgs.model.surfels import SurfelModel, jagged_offsets

    gen = torch.Generator().manual_seed(8)
    n = 57
    tex_res = torch.randint(0, 6, (n, 2), generator=gen, dtype=torch.int32)
    t = int((tex_res[:, 0].long() * tex_res[:, 1].long()).sum())
    model = SurfelModel(
        means=torch.randn(n, 3, dtype=dtype), log_scales=torch.zeros(n, 2, dtype=dtype),
        quats=torch.randn(n, 4, dtype=dtype), opacity_logits=torch.zeros(n, dtype=dtype),
        sh=torch.zeros(n, 1, 3, dtype=dtype), textures_raw=torch.randn(t, 3, generator=gen, dtype=dtype) * 3,
        k_min=torch.full((n,), 0.05, dtype=dtype), t2p_exp=torch.ones(n, dtype=torch.int32), tex_res=tex_res,
        tex_offset=jagged_offsets(tex_res), texture_mode="content_aware")
    model.textures_raw.requires_grad_(True)
    weight = (torch.rand(n, generator=gen) > 0.3).to(dtype) * torch.rand(n, generator=gen, dtype=dtype)
    a = fused.texel_l1(model, weight)
    (ga,) = torch.autograd.grad(2.0 * a, model.textures_raw)
    y = model.textures
    b = fused.texel_l1(model, weight, y)
    (gb,) = torch.autograd.grad(2.0 * b, model.textures_raw)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    torch.testing.assert_close(ga, gb, rtol=tol, atol=tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_regulariser_folded_into_the_activation_backward_is_bit_identical(dtype):
    """texel_l1 on the activation's own output defers its gradient to the activation's backward (one pass
    instead of a [T, 3] gradient, autograd's sum and the activation backward): raw's gradient is the
    plain chain's bit for bit, with a second consumer of y (as the render is), with zero weights and with
    the term alone; with two terms on the same y, to rounding (three gradients of y summed in another order)."""
    from ctgs.model.surfels import SurfelModel, jagged_offsets

    gen = torch.Generator().manual_seed(9)
    n = 301
    tex_res = torch.randint(0, 7, (n, 2), generator=gen, dtype=torch.int32)
    t = int((tex_res[:, 0].long() * tex_res[:, 1].long()).sum())
    raw = torch.randn(t, 3, generator=gen, dtype=dtype) * 3
    raw[:5] = 0.0  # sign(y) = 0
    model = SurfelModel(
        means=torch.randn(n, 3, dtype=dtype), log_scales=torch.zeros(n, 2, dtype=dtype),
        quats=torch.randn(n, 4, dtype=dtype), opacity_logits=torch.zeros(n, dtype=dtype),
        sh=torch.zeros(n, 1, 3, dtype=dtype), textures_raw=raw.requires_grad_(True),
        k_min=torch.full((n,), 0.05, dtype=dtype), t2p_exp=torch.ones(n, dtype=torch.int32), tex_res=tex_res,
        tex_offset=jagged_offsets(tex_res), texture_mode="content_aware")
    weight = (torch.rand(n, generator=gen) > 0.3).to(dtype) * torch.rand(n, generator=gen, dtype=dtype)
    other = torch.randn(t, 3, generator=gen, dtype=dtype)  # stands in for the render's use of y

    def grads(defer: bool, with_other: bool = True, terms: int = 1):
        y = model.textures
        if not defer:
            y = y.view_as(y)  # a new tensor object: no deferred holder, the plain autograd path
        loss = (y * other).sum() if with_other else y.new_zeros(())
        for k in range(terms):
            loss = loss + (1e-3 * (k + 1)) * fused.texel_l1(model, weight * (k + 1), y)
        (g,) = torch.autograd.grad(loss, model.textures_raw)
        return g

    assert hasattr(model.textures, "_ctgs_deferred_l1")
    for kwargs in ({}, {"with_other": False}):
        a, b = grads(True, **kwargs), grads(False, **kwargs)
        assert torch.equal(a, b), kwargs
        assert a.abs().sum() > 0
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(grads(True, terms=2), grads(False, terms=2), rtol=tol, atol=tol)
    zero = torch.zeros_like(weight)
    y = model.textures
    (g,) = torch.autograd.grad((y * other).sum() + fused.texel_l1(model, zero, y), model.textures_raw)
    (h,) = torch.autograd.grad((model.textures * other).sum(), model.textures_raw)
    assert torch.equal(g, h)
