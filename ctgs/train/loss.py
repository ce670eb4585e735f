"""Training loss (paper 3.4): (1-l) L1 + l (1-SSIM) + opacity regulariser + texture sparsity on visible primitives."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ctgs.metrics.ssim import ssim_map
from ctgs.fused import texel_l1


@dataclass
class LossTerms:
    total: torch.Tensor  # scalar, differentiable
    l1: float
    ssim: float
    psnr: float


def visible_mask(means: torch.Tensor, camera) -> torch.Tensor:
    """[N] bool: centre in front of the camera and projecting inside the image."""
    vm = camera.viewmat.to(means.device, means.dtype)
    pc = means.detach() @ vm[:3, :3].T + vm[:3, 3]
    z = pc[:, 2]
    zs = z.clamp_min(1e-12)
    u = camera.fx * pc[:, 0] / zs + camera.cx
    v = camera.fy * pc[:, 1] / zs + camera.cy
    return (z > camera.near) & (u >= 0) & (u <= camera.width) & (v >= 0) & (v <= camera.height)


def training_loss(render: torch.Tensor, gt: torch.Tensor, model, camera, cfg) -> LossTerms:
    """render, gt: [H, W, 3] in [0, 1]."""
    l1 = (render - gt).abs().mean()
    s = ssim_map(render, gt).mean()
    total = (1 - cfg.lambda_ssim) * l1 + cfg.lambda_ssim * (1 - s)
    if cfg.lambda_opacity > 0:
        total = total + cfg.lambda_opacity * model.opacities.mean()
    if cfg.lambda_texture > 0 and model.texture_mode != "none" and model.num_texels > 0:
        vis = visible_mask(model.means, camera)
        # The data term is a mean over pixels, so its gradient per texel shrinks as 1/(H*W) while the
        # sparsity term's does not: texture_reg_pixels keeps the paper's balance on smaller images.
        lam = cfg.lambda_texture
        if cfg.texture_reg_pixels > 0:
            lam = lam * cfg.texture_reg_pixels / (gt.shape[0] * gt.shape[1])
        total = total + lam * texel_l1(model, vis)  # sum |texel| over visible primitives (fused on CPU)
    mse = ((render.detach() - gt) ** 2).mean().clamp_min(1e-12)
    return LossTerms(total=total, l1=float(l1.detach()), ssim=float(s.detach()), psnr=float(-10 * torch.log10(mse)))
