"""Training loss (paper 3.4): (1-l) L1 + l (1-SSIM) + opacity regulariser + texture sparsity on visible primitives.

"Visible" is what the rasterizer saw, as in the authors' release (their `radii > 0`): the primitives the
CPU/CUDA binning keeps for the view (`rasterized_mask`). The texture term is plain L1 by default (the
paper and the released code); `texture_reg_transmittance` weights each primitive's L1 by one minus its
mean transmittance in the view, the variant the authors' README says the paper's runs used (hidden
primitives are regularised more; the released code has it commented out beside the plain line).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ctgs.metrics.ssim import ssim_map
from ctgs.ops.fused import photometric_loss as fused_photometric_loss
from ctgs.ops.fused import texel_l1
from ctgs.render import render
from ctgs.render.constants import CUTOFF_RHO, FILTER_INV_SQUARE, MAX_ALPHA, MIN_ALPHA
from ctgs.render.geometry import quat_to_rotmat

# surfel_pixel_rect (kernels/include/ctgs/bounds.h): the screen-space fallback box around the projected
# centre, in pixels, and the object-space corners at +-3 sigma (CUTOFF_RHO = 9).
FALLBACK_RADIUS_PX = math.sqrt(CUTOFF_RHO / FILTER_INV_SQUARE)
CUTOFF_SIGMA = math.sqrt(CUTOFF_RHO)
_CORNER_SIGNS = ((-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0))  # (u, v) signs of the 4 corners


@dataclass
class LossTerms:
    total: torch.Tensor  # scalar, differentiable
    l1: float
    ssim: float
    psnr: float
    error_image: torch.Tensor | None = None  # [H, W] the photometric error per pixel (want_error), detached


@torch.no_grad()
def rasterized_mask(model, camera) -> torch.Tensor:
    """[N] bool: the primitives the rasterizer keeps for `camera` (kernels/cpu/binning.cpp, CUDA alike):
    centre depth >= near, opacity >= MIN_ALPHA, and a non-empty pixel rectangle (bounds.h surfel_pixel_rect:
    the projected +-3 sigma corners united with the fallback box around the projected centre; a corner
    before the near plane makes the rectangle the whole image). Same float ops and order as the kernels,
    in the model's dtype, so the set matches the kernels' binning exactly (tests/train/test_loss_visibility)."""
    means = model.means.detach()
    vm = camera.viewmat.to(means.device, means.dtype)
    rv, tv = vm[:3, :3], vm[:3, 3]
    mu = means @ rv.T + tv  # [N, 3] camera space, as ctgs.render.preprocess computes it
    rc = rv @ quat_to_rotmat(model.quats.detach())  # [N, 3, 3] columns u, v, n
    s = model.scales.detach()  # [N, 2] world units
    z = mu[:, 2]
    kept = (z >= camera.near) & (model.opacities.detach() >= MIN_ALPHA)
    mx = camera.fx * mu[:, 0] / z + camera.cx  # [N] projected centre, pixels
    my = camera.fy * mu[:, 1] / z + camera.cy
    a = (CUTOFF_SIGMA * s[:, 0])[:, None] * rc[:, :, 0]  # [N, 3]
    b = (CUTOFF_SIGMA * s[:, 1])[:, None] * rc[:, :, 1]
    signs = torch.tensor(_CORNER_SIGNS, dtype=means.dtype, device=means.device)  # [4, 2]
    corners = mu[:, None] + signs[None, :, 0, None] * a[:, None] + signs[None, :, 1, None] * b[:, None]  # [N, 4, 3]
    straddles = ~(corners[..., 2] >= camera.near).all(1)  # [N] (NaN counts as straddling, as in the kernel)
    px = camera.fx * corners[..., 0] / corners[..., 2] + camera.cx  # [N, 4]
    py = camera.fy * corners[..., 1] / corners[..., 2] + camera.cy
    xmin = torch.minimum(mx - FALLBACK_RADIUS_PX, px.min(1).values)
    xmax = torch.maximum(mx + FALLBACK_RADIUS_PX, px.max(1).values)
    ymin = torch.minimum(my - FALLBACK_RADIUS_PX, py.min(1).values)
    ymax = torch.maximum(my + FALLBACK_RADIUS_PX, py.max(1).values)
    off_image = (xmax < 0) | (ymax < 0) | (xmin > camera.width) | (ymin > camera.height)
    return kept & (straddles | ~off_image)


def _mean_alpha_alone(o: torch.Tensor) -> torch.Tensor:
    """[N] mean alpha = min(MAX_ALPHA, o G) of an unoccluded surfel over the pixels it is blended at.

    Those pixels are rho <= rho_c = min(CUTOFF_RHO, 2 ln(o / MIN_ALPHA)); pixel centres sample the
    (locally affine) footprint uniformly in area, and area grows linearly in rho, so the mean is
    (1 / rho_c) * integral_0^rho_c min(MAX_ALPHA, o exp(-rho / 2)) d rho."""
    rho_c = (2 * torch.log((o / MIN_ALPHA).clamp_min(1.0))).clamp(max=CUTOFF_RHO)
    rho_0 = (2 * torch.log((o / MAX_ALPHA).clamp_min(1.0))).clamp(max=rho_c)  # below it alpha is clamped
    area = MAX_ALPHA * rho_0 + 2 * o * (torch.exp(-rho_0 / 2) - torch.exp(-rho_c / 2))
    return area / rho_c.clamp_min(1e-12)


@torch.no_grad()
def mean_transmittance(stats, opacities: torch.Tensor) -> torch.Tensor:
    """[N] estimated transmittance in front of each primitive, averaged over the pixels it is blended at.

    The renderer's statistics give count (pixels blended) and contrib = sum over them of alpha * T. Dividing
    by the sum of alpha a lone surfel of that opacity would have there (count * `_mean_alpha_alone`) gives
    the alpha-weighted mean of T: exact when T is uniform over the footprint, 1 for an unoccluded surfel,
    and 0 for a primitive blended nowhere. (The authors accumulate sum T directly; that needs one more
    kernel accumulator next to contrib.)"""
    count = stats.count.to(opacities.dtype)
    expected = count * _mean_alpha_alone(opacities.detach())
    return torch.where(count > 0, stats.contrib / expected.clamp_min(1e-12), 0.0).clamp(0.0, 1.0)


def texture_weights(model, camera, cfg, stats=None, rasterized=None) -> torch.Tensor:
    """[N] weight of each primitive's texel L1: 1 for rasterized primitives (0 otherwise), times 1 - mean
    transmittance with cfg.texture_reg_transmittance. `stats`: this view's ErrorStats if the caller rendered
    them already; otherwise one extra forward pass computes them. `rasterized`: the render's own [N] mask
    (RenderOutput.rasterized) if it has one; otherwise `rasterized_mask` recomputes the same set."""
    if rasterized is None or rasterized.shape != (model.num_primitives,):
        rasterized = rasterized_mask(model, camera)
    weights = rasterized.to(model.means.dtype)
    if cfg.texture_reg_transmittance:
        if stats is None:
            with torch.no_grad():
                zeros = model.means.new_zeros(camera.height, camera.width)
                stats = render(model.render_inputs(), camera, backend=cfg.backend, sh_degree=model.sh_degree,
                               error_image=zeros).stats
        weights = weights * (1.0 - mean_transmittance(stats, model.opacities))
    return weights


def masked(rgb: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """(rgb, gt) with both zero where `mask` ([H, W, 1] bool, None: every pixel used) leaves pixels out (a view's
    mask, ctgs.scene.photos): no error and no gradient there, and no SSIM window sees the photo's values there."""
    if mask is None:
        return rgb, gt
    zero = rgb.new_zeros(())
    return torch.where(mask, rgb, zero), torch.where(mask, gt, zero)


def recomposited(gt: torch.Tensor, alpha: torch.Tensor | None, base: torch.Tensor, bg: torch.Tensor) -> torch.Tensor:
    """A transparent photo `gt` ([H, W, 3], composited over `base` [3]) over `bg` [3] instead, from its alpha
    ([H, W, 1]; None: an opaque photo, returned as it is)."""
    return gt if alpha is None else gt + (bg - base) * (1 - alpha)


def photometric_loss(render: torch.Tensor, gt: torch.Tensor, lambda_ssim: float, want_error: bool = False):
    """(1 - lambda_ssim) mean |render - gt| + lambda_ssim (1 - mean SSIM) of two [H, W, C] images (SSIM as
    ctgs.metrics.ssim): (total, differentiable w.r.t. render; mean L1 and mean SSIM, detached), and with want_error
    the error image of the same pass, e [H, W] = (1 - l) mean_c |render - gt| + l mean_c (1 - SSIM map) (detached).
    One compiled pass on the CPU (ctgs.ops.fused.photometric_loss), this PyTorch expression elsewhere."""
    if render.shape != gt.shape or render.ndim != 3:
        raise ValueError(f"photometric_loss expects two [H, W, C] images of one shape, got {list(render.shape)}, "
                         f"{list(gt.shape)}")
    fused = fused_photometric_loss(render, gt, lambda_ssim, want_error)
    if fused is not None:
        return fused
    l1_map = (render - gt).abs()
    s_map = ssim_map(render, gt)
    total = (1 - lambda_ssim) * l1_map.mean() + lambda_ssim * (1 - s_map.mean())
    if not want_error:
        return total, l1_map.mean().detach(), s_map.mean().detach()
    e = ((1 - lambda_ssim) * l1_map.mean(-1) + lambda_ssim * (1 - s_map).mean(-1)).detach()
    return total, l1_map.mean().detach(), s_map.mean().detach(), e


def training_loss(render: torch.Tensor, gt: torch.Tensor, model, camera, cfg, stats=None,
                  rasterized=None, textures=None, want_error: bool = False) -> LossTerms:
    """render, gt: [H, W, 3] in [0, 1]; stats: the view's ErrorStats, if rendered; rasterized: the render's
    [N] mask of rasterized primitives, if it has one (see texture_weights); textures: the activated texel
    offsets the render used (SurfelInputs.textures), if the caller kept them (see ctgs.ops.fused.texel_l1);
    want_error: also the photometric error image of the pass (LossTerms.error_image: E's per-pixel error)."""
    # (1 - l) L1 + l (1 - SSIM): one fused pass, gradient included, on the CPU (kernels/cpu/ssim.cpp).
    total, l1, s, *error = photometric_loss(render, gt, cfg.lambda_ssim, want_error=want_error)
    if cfg.lambda_opacity > 0:
        if cfg.opacity_reg_visible:
            # Only what this view rasterizes: a primitive no view shows gets no gradient, so Adam cannot move it
            # (a constant gradient alone is a full-lr step per iteration, whatever its size).
            if rasterized is None or rasterized.shape != (model.num_primitives,):
                rasterized = rasterized_mask(model, camera)
            opacity = (model.opacities * rasterized.to(model.opacities.dtype)).sum() / max(model.num_primitives, 1)
        else:
            opacity = model.opacities.mean()
        total = total + cfg.lambda_opacity * opacity
    if cfg.lambda_texture > 0 and model.texture_mode != "none" and model.num_texels > 0:
        weights = texture_weights(model, camera, cfg, stats, rasterized)  # [N]
        # cfg.lambda_texture is already resolved for the image size (ctgs/train/config/rules.py: x 1e6 / (H*W)).
        # sum_i weights[i] sum |texel of i|: one fused pass on the CPU, no [T] weight tensor.
        total = total + cfg.lambda_texture * texel_l1(model, weights, textures)
    mse = ((render.detach() - gt) ** 2).mean().clamp_min(1e-12)
    return LossTerms(total=total, l1=float(l1), ssim=float(s), psnr=float(-10 * torch.log10(mse)),
                     error_image=error[0] if error else None)
