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


def gain_matched_psnr(render: torch.Tensor, gt: torch.Tensor) -> tuple[float, float]:
    """(g, PSNR of clamp(g x render, 0, 1) against gt) with g = <render, gt> / <render, render>, the one gain that best
    maps the render to the photo (least squares over all pixels and channels; 1 for an all-black render). A
    diagnostic of exposure: a new view's exposure is unknown to any method, so this is not the protocol's PSNR."""
    r, g = render.double(), gt.double()
    den = float((r * r).sum())
    gain = float((r * g).sum()) / den if den > 0 else 1.0
    return gain, psnr((r * gain).clamp(0.0, 1.0), g)


def masked_psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float | None:
    """PSNR over the pixels where `mask` [H, W] is True (every channel); None when it selects none."""
    if a.shape != b.shape or tuple(mask.shape) != tuple(a.shape[:2]):
        raise ValueError(f"masked_psnr expects images of one shape and an [H, W] mask, got {list(a.shape)}, "
                         f"{list(b.shape)} and {list(mask.shape)}")
    if not bool(mask.any()):
        return None
    mse = float(((a.double() - b.double()) ** 2)[mask].mean())
    return -10.0 * math.log10(max(mse, MIN_MSE))
