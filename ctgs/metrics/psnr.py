"""PSNR of images in [0, 1] (peak 1), the 3DGS evaluation definition."""

from __future__ import annotations

import math

import torch

# An exact match would give +inf, which JSON cannot hold: MSE is floored, capping PSNR at 100 dB.
MIN_MSE = 1e-10


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR in dB of two same-shape images with values in [0, 1] (MSE over all pixels and channels)."""
    if a.shape != b.shape:
        raise ValueError(f"psnr expects images of one shape, got {list(a.shape)} and {list(b.shape)}")
    mse = float(((a.double() - b.double()) ** 2).mean())
    return -10.0 * math.log10(max(mse, MIN_MSE))


def masked_psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float | None:
    """PSNR over the pixels where `mask` [H, W] is True (every channel); None when it selects none."""
    if a.shape != b.shape or tuple(mask.shape) != tuple(a.shape[:2]):
        raise ValueError(f"masked_psnr expects images of one shape and an [H, W] mask, got {list(a.shape)}, "
                         f"{list(b.shape)} and {list(mask.shape)}")
    if not bool(mask.any()):
        return None
    mse = float(((a.double() - b.double()) ** 2)[mask].mean())
    return -10.0 * math.log10(max(mse, MIN_MSE))
