"""The compiled world -> camera transform (kernels/cpu/camera.cpp via ctgs.render.preprocess.camera_space)
against the PyTorch expression it replaces (camera_space_torch): values and gradients w.r.t. means and raw
quaternions in float32 and float64, quaternions of any norm (a zero one included: the 1e-12 clamp),
gradcheck, only one output used, and the fallback off the CPU path."""

from __future__ import annotations

import pytest
import torch
from scenes import look_at

from ctgs.ops import fused
from ctgs.render.preprocess import _CameraSpace, camera_space, camera_space_torch

TOL = {torch.float32: 3e-6, torch.float64: 1e-13}


def _inputs(n: int, dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2.0
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64) * torch.rand(n, 1, generator=g, dtype=torch.float64) * 3
    quats[0] = 0.0  # degenerate: normalised with the clamped norm, R = identity
    quats[1] = torch.tensor([1e-13, 0.0, 2e-13, 0.0])  # below the clamp
    view = look_at((0.4, -0.3, -2.5), (0.1, 0.2, 0.0))
    return means.to(dtype), quats.to(dtype), view.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_camera_space_matches_pytorch(dtype):
    assert fused.cpu_ext() is not None
    means, quats, view = _inputs(333, dtype)
    m1, q1 = means.clone().requires_grad_(), quats.clone().requires_grad_()
    m2, q2 = means.clone().requires_grad_(), quats.clone().requires_grad_()
    mu1, R1 = camera_space(m1, q1, view)
    mu2, R2 = camera_space_torch(m2, q2, view)
    assert mu1.grad_fn is not None and "CameraSpace" in type(mu1.grad_fn).__name__
    torch.testing.assert_close(mu1, mu2, rtol=TOL[dtype], atol=TOL[dtype])
    torch.testing.assert_close(R1, R2, rtol=TOL[dtype], atol=TOL[dtype])
    g = torch.Generator().manual_seed(5)
    up_mu = torch.randn(mu1.shape, generator=g, dtype=torch.float64).to(dtype)
    up_R = torch.randn(R1.shape, generator=g, dtype=torch.float64).to(dtype)
    ((mu1 * up_mu).sum() + (R1 * up_R).sum()).backward()
    ((mu2 * up_mu).sum() + (R2 * up_R).sum()).backward()
    torch.testing.assert_close(m1.grad, m2.grad, rtol=10 * TOL[dtype], atol=10 * TOL[dtype])
    # Quaternion gradients scale with 1 / |q|: compare relative to their size (1e12 for the clamped ones).
    scale = q2.grad.abs().amax(dim=1, keepdim=True).clamp_min(1.0)
    torch.testing.assert_close(q1.grad / scale, q2.grad / scale, rtol=10 * TOL[dtype], atol=10 * TOL[dtype])


def test_camera_space_gradcheck():
    means, quats, view = _inputs(7, torch.float64, seed=2)
    quats[:2] = torch.tensor([[0.9, 0.1, -0.3, 0.2], [0.2, 0.5, 0.1, -0.7]], dtype=torch.float64)  # away from the clamp
    m, q = means.requires_grad_(), quats.requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: _CameraSpace.apply(a, b, view), (m, q))


def test_one_output_unused():
    """Only Rc (or only mu_c) in the loss: the other's missing gradient counts as zero."""
    means, quats, view = _inputs(20, torch.float64, seed=3)
    q1, q2 = quats.clone().requires_grad_(), quats.clone().requires_grad_()
    m1, m2 = means.clone().requires_grad_(), means.clone().requires_grad_()
    camera_space(m1, q1, view)[1].sum().backward()
    camera_space_torch(m2, q2, view)[1].sum().backward()
    torch.testing.assert_close(q1.grad, q2.grad, rtol=1e-12, atol=1e-12)
    assert m1.grad is None or bool((m1.grad == 0).all())


def test_falls_back_when_the_view_needs_a_gradient():
    means, quats, view = _inputs(5, torch.float64, seed=4)
    view = view.clone().requires_grad_()
    mu, R = camera_space(means, quats, view)
    assert "CameraSpace" not in type(mu.grad_fn).__name__
    (mu.sum() + R.sum()).backward()
    assert view.grad is not None
