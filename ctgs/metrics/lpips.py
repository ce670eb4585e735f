"""LPIPS (Zhang et al. 2018), VGG variant, version 0.1: own torch VGG16 trunk (no torchvision).

The linear layers are the `lpips` package's v0.1 VGG weights, vendored in `weights/` with their BSD
licence (7 KB). The VGG16 trunk weights come from `vgg_weights.find_vgg16`. Inputs follow the lpips
package: images in [-1, 1]; `normalize=True` maps [0, 1] to [-1, 1]. ctgs' eval feeds [0, 1] images
*without* rescaling (normalize=False), the 3DGS/2DGS evaluation convention, so its numbers compare with
the paper's tables; docs/reference/metrics.md states this.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ctgs.metrics.vgg_weights import CONV_INDICES, find_vgg16

LIN_WEIGHTS = os.path.join(os.path.dirname(__file__), "weights", "lpips_vgg_v0.1.pth")
# lpips' ScalingLayer: ImageNet statistics expressed for inputs in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# Feature taps: after the ReLU of features[3], [8], [15], [22], [29] (relu1_2 ... relu5_3).
TAP_AFTER_CONV = (1, 3, 6, 9, 12)  # index into CONV_INDICES of the last conv before each tap
POOL_AFTER_CONV = (1, 3, 6, 9)  # max-pool 2x2 follows these convs
NORM_EPS = 1e-10  # lpips' normalize_tensor epsilon


@dataclass
class LpipsStatus:
    available: bool
    detail: str  # weights source, or "unavailable: <reason>"


class LPIPS(torch.nn.Module):
    """LPIPS-VGG v0.1 distance; `forward(a, b)` takes [B, 3, H, W] and returns [B]."""

    def __init__(self, vgg_state: dict[str, torch.Tensor]):
        super().__init__()
        self.convs = torch.nn.ModuleList()
        for i in CONV_INDICES:
            w = vgg_state[f"features.{i}.weight"]
            conv = torch.nn.Conv2d(w.shape[1], w.shape[0], 3, padding=1)
            conv.weight.data.copy_(w)
            conv.bias.data.copy_(vgg_state[f"features.{i}.bias"])
            self.convs.append(conv)
        lin = torch.load(LIN_WEIGHTS, map_location="cpu", weights_only=True)
        for k in range(5):
            self.register_buffer(f"lin{k}", lin[f"lin{k}.model.1.weight"].float())  # [1, C, 1, 1]
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.shift) / self.scale
        taps = []
        for j, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            if j in TAP_AFTER_CONV:
                taps.append(x)
            if j in POOL_AFTER_CONV:
                x = F.max_pool2d(x, 2, 2)
        return taps

    def forward(self, a: torch.Tensor, b: torch.Tensor, normalize: bool = False) -> torch.Tensor:
        if normalize:
            a, b = 2 * a - 1, 2 * b - 1
        total = 0.0
        for k, (fa, fb) in enumerate(zip(self.features(a), self.features(b))):
            fa = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + NORM_EPS)
            fb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + NORM_EPS)
            d = F.conv2d((fa - fb) ** 2, getattr(self, f"lin{k}"))  # [B, 1, h, w]
            total = total + d.mean(dim=(1, 2, 3))
        return total


_CACHE: dict = {}


def load_lpips(weights: str | None = None, device: torch.device | str = "cpu") -> tuple[LPIPS | None, LpipsStatus]:
    """The LPIPS network, or None and the reason it is unavailable (never a made-up number)."""
    key = (weights, str(device))
    if key not in _CACHE:
        found = find_vgg16(weights)
        if found.state is None:
            _CACHE[key] = (None, LpipsStatus(False, "unavailable: " + found.source))
        else:
            _CACHE[key] = (LPIPS(found.state).to(device), LpipsStatus(True, found.source))
    return _CACHE[key]


@torch.no_grad()
def lpips_hwc(net: LPIPS, a, b) -> float:
    """LPIPS of two [H, W, 3] images in [0, 1] (torch or numpy), fed as [0, 1] (3DGS convention)."""
    dev = net.shift.device
    ta = torch.as_tensor(a, dtype=torch.float32, device=dev).permute(2, 0, 1)[None]
    tb = torch.as_tensor(b, dtype=torch.float32, device=dev).permute(2, 0, 1)[None]
    return float(net(ta, tb)[0])
