"""Real spherical harmonics -> view-dependent colour, 3DGS layout and constants (degrees 0..3)."""

from __future__ import annotations

import torch

from ctgs.ops.dispatch import fusable_here

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_coeffs(degree: int) -> int:
    return (degree + 1) ** 2


def sh_to_color(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """sh [N, K, 3] with K >= (degree+1)^2, unit view directions dirs [N, 3] -> colour [N, 3] = SH + 0.5.

    Not clamped (the renderer clamps after adding the texture).
    """
    out = SH_C0 * sh[:, 0]
    if degree >= 1:
        x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]  # [N, 1] each
        out = out - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
        if degree >= 2:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            out = (out + SH_C2[0] * xy * sh[:, 4] + SH_C2[1] * yz * sh[:, 5]
                   + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6] + SH_C2[3] * xz * sh[:, 7]
                   + SH_C2[4] * (xx - yy) * sh[:, 8])
            if degree >= 3:
                out = (out + SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9] + SH_C3[1] * xy * z * sh[:, 10]
                       + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
                       + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
                       + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13] + SH_C3[5] * z * (xx - yy) * sh[:, 14]
                       + SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15])
    return out + 0.5


def view_dirs(means: torch.Tensor, camera_center: torch.Tensor) -> torch.Tensor:
    """normalize(mean - camera centre) [N, 3]; a mean exactly at the centre gets direction 0 (no NaN)."""
    d = means - camera_center
    sq = (d * d).sum(-1, keepdim=True)
    nonzero = sq > 0
    return d * torch.where(nonzero, torch.rsqrt(torch.where(nonzero, sq, torch.ones_like(sq))), 0.0)


class _ShColor(torch.autograd.Function):
    """sh_to_color(sh, view_dirs(means, center), degree) in one compiled pass (kernels/include/ctgs/preprocess.h:
    kernels/cpu/sh.cpp on the CPU, kernels/cuda/dense.cu on a GPU)."""

    @staticmethod
    def forward(ctx, means, sh, center, degree):
        ctx.save_for_backward(means, sh, center)
        ctx.degree = degree
        return torch.ops.ctgs.sh_color(means, center, sh, degree, torch.get_num_threads())

    @staticmethod
    def backward(ctx, grad_colors):
        means, sh, center = ctx.saved_tensors
        gm, gs = torch.ops.ctgs.sh_color_backward(means, center, sh, ctx.degree, grad_colors.contiguous(),
                                                  torch.get_num_threads())
        return (gm if ctx.needs_input_grad[0] else None), (gs if ctx.needs_input_grad[1] else None), None, None


def view_color(means: torch.Tensor, sh: torch.Tensor, center: torch.Tensor, degree: int) -> torch.Tensor:
    """[N, 3] = sh_to_color(sh, view_dirs(means, center), degree): differentiable w.r.t. means and sh (not the
    centre). On the CPU and on a GPU one compiled pass each way instead of ~150 small PyTorch ops per training
    step; the same values to float rounding (tests/render/test_sh.py, tests/render/test_cuda_backend.py)."""
    if (not center.requires_grad and 0 <= degree <= 3 and sh.ndim == 3 and sh.shape[2] == 3
            and sh.shape[1] >= num_sh_coeffs(degree) and means.ndim == 2 and means.shape[1] == 3
            and sh.dtype == means.dtype and sh.device == means.device):
        m, s, c = means.contiguous(), sh.contiguous(), center.detach().to(means.device, means.dtype).contiguous()
        if fusable_here(m, s, c):
            return _ShColor.apply(m, s, c, int(degree))
    return sh_to_color(sh, view_dirs(means, center), degree)
