"""Differentiable SSIM (Wang et al. 2004) with the 3DGS/2DGS convention: 11x11 Gaussian window,
sigma 1.5, C1 = 0.01^2, C2 = 0.03^2 (images in [0, 1]), zero padding ("same" size map).

Used by evaluation, and by the training loss and the per-primitive error image E off the CPU; on the CPU those
two use the compiled pass of kernels/cpu/ssim.cpp (ctgs.ops.fused.photometric_loss / error_image), the same
formula to float rounding (tests/train/test_fused.py), so all three agree.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

WINDOW_SIZE = 11
WINDOW_SIGMA = 1.5
C1 = 0.01 ** 2
C2 = 0.03 ** 2

_WINDOWS: dict[tuple, torch.Tensor] = {}


def _window(channels: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """[channels, 1, 1, 11] normalised 1D Gaussian (the 2D window is separable: two 1D passes)."""
    key = (channels, dtype, str(device))
    if key not in _WINDOWS:
        x = torch.arange(WINDOW_SIZE, dtype=torch.float64) - WINDOW_SIZE // 2
        g = torch.exp(-(x ** 2) / (2 * WINDOW_SIGMA ** 2))
        g = (g / g.sum()).to(dtype=dtype, device=device)
        _WINDOWS[key] = g.view(1, 1, 1, WINDOW_SIZE).expand(channels, 1, 1, WINDOW_SIZE).contiguous()
    return _WINDOWS[key]


def _blur(x: torch.Tensor) -> torch.Tensor:
    """Gaussian window of every channel of x [1, C, H, W], zero padded, same size (separable: ~5x cheaper)."""
    c = x.shape[1]
    w = _window(c, x.dtype, x.device)
    pad = WINDOW_SIZE // 2
    x = F.conv2d(x, w, padding=(0, pad), groups=c)
    return F.conv2d(x, w.transpose(2, 3), padding=(pad, 0), groups=c)


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of two [H, W, C] images in [0, 1] -> [H, W, C] (differentiable)."""
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"ssim_map expects two [H, W, C] images of one shape, got {list(a.shape)}, {list(b.shape)}")
    c = a.shape[2]
    x = a.permute(2, 0, 1)[None]  # [1, C, H, W]
    y = b.permute(2, 0, 1)[None]
    # One blur for all five moments: fewer kernel launches matter on 2 CPU cores.
    mu_x, mu_y, sxx, syy, sxy = _blur(torch.cat([x, y, x * x, y * y, x * y], 1)).split(c, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    sigma_x, sigma_y, sigma_xy = sxx - mu_xx, syy - mu_yy, sxy - mu_xy
    num = (2 * mu_xy + C1) * (2 * sigma_xy + C2)
    den = (mu_xx + mu_yy + C1) * (sigma_x + sigma_y + C2)
    return (num / den)[0].permute(1, 2, 0)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H, W, C] images in [0, 1] -> scalar tensor (differentiable)."""
    return ssim_map(a, b).mean()


def masked_ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean SSIM over the pixels where `mask` [H, W] is True (a view's mask: the pixels left out count nowhere; they
    are zero in both images, so that no window sees their values)."""
    keep = mask[..., None]
    zero = a.new_zeros(())
    return float(ssim_map(torch.where(keep, a, zero), torch.where(keep, b, zero))[mask].mean()) \
        if bool(mask.any()) else float("nan")
