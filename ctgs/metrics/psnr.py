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
