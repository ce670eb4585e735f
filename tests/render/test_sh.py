"""The compiled view-dependent colour (kernels/cpu/sh.cpp via ctgs.render.sh.view_color) against the PyTorch
expression it replaces (sh_to_color of view_dirs): values and gradients w.r.t. means and SH at every degree,
in float32 and float64, a mean exactly at the camera centre, gradcheck, threads."""

from __future__ import annotations

import pytest
import torch

from ctgs.ops import fused
from ctgs.render.sh import sh_to_color, view_color, view_dirs

TOL = {torch.float32: 2e-6, torch.float64: 1e-13}


def _inputs(n: int, k: int, dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 2.0
    sh = torch.randn(n, k, 3, generator=g, dtype=dtype) * 0.5
    center = torch.tensor([0.3, -0.2, 0.5], dtype=dtype)
    means[0] = center  # direction 0: colour SH_C0 * sh[0] + 0.5, no gradient to the mean
    return means, sh, center


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_view_color_matches_pytorch(dtype, degree):
    assert fused.cpu_ext() is not None
    means, sh, center = _inputs(517, 16, dtype, degree)
    m1, s1 = means.clone().requires_grad_(), sh.clone().requires_grad_()
    m2, s2 = means.clone().requires_grad_(), sh.clone().requires_grad_()
    c1 = view_color(m1, s1, center, degree)
    c2 = sh_to_color(s2, view_dirs(m2, center), degree)
    torch.testing.assert_close(c1, c2, rtol=TOL[dtype], atol=TOL[dtype])
    up = torch.randn(c1.shape, generator=torch.Generator().manual_seed(9), dtype=dtype)
    (c1 * up).sum().backward()
    (c2 * up).sum().backward()
    # Degree 0 does not depend on the direction: PyTorch leaves no gradient, the kernel writes zeros.
    ref_m = torch.zeros_like(means) if m2.grad is None else m2.grad
    torch.testing.assert_close(m1.grad, ref_m, rtol=10 * TOL[dtype], atol=10 * TOL[dtype])
    torch.testing.assert_close(s1.grad, s2.grad, rtol=TOL[dtype], atol=TOL[dtype])
    assert torch.all(s1.grad[:, (degree + 1) ** 2:] == 0)
    assert torch.all(m1.grad[0] == 0)  # the mean at the camera centre


def test_view_color_gradcheck_and_threads():
    means, sh, center = _inputs(23, 16, torch.float64, 4)
    means, sh = means[1:].clone().requires_grad_(), sh[1:].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda m, s: view_color(m, s, center, 3), (means, sh))
    assert fused.cpu_ext() is not None  # loaded: its kernels serve torch.ops.ctgs on the CPU
    m, s, c = _inputs(1000, 9, torch.float32, 5)
    outs = [torch.ops.ctgs.sh_color(m, c, s, 2, t) for t in (1, 2, 3)]
    assert all(torch.equal(o, outs[0]) for o in outs)
    gc = torch.ones(1000, 3)
    grads = [torch.ops.ctgs.sh_color_backward(m, c, s, 2, gc, t) for t in (1, 2)]
    assert all(torch.equal(a, b) for a, b in zip(*grads))


def test_view_color_rejects_a_degree_the_coefficients_cannot_hold():
    means, sh, center = _inputs(10, 4, torch.float32)
    with pytest.raises(RuntimeError, match="degree"):
        torch.ops.ctgs.sh_color(means, center, sh, 2, 1)
    # The Python entry falls back to PyTorch, which raises its own error for a missing coefficient.
    with pytest.raises(IndexError):
        view_color(means, sh, center, 2)
