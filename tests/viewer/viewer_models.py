"""Small textured surfel models and cameras for the viewer tests (no training)."""

from __future__ import annotations

import math

import torch

from ctgs.model.surfels import SurfelModel, jagged_offsets
from ctgs.render.camera import Camera


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """World->camera 4x4 float32 for a camera at `eye` looking at `target` (OpenCV: +z forward, y down)."""
    eye, target, up = (torch.tensor(a, dtype=torch.float64) for a in (eye, target, up))
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = torch.stack([x, y, z])
    view[:3, 3] = -view[:3, :3] @ eye
    return view.float()


def camera(width: int = 64, height: int = 48, eye=(0.3, -0.2, -2.6)) -> Camera:
    return Camera(fx=1.1 * width, fy=1.1 * width, cx=width / 2 + 0.3, cy=height / 2 - 0.2, width=width,
                  height=height, viewmat=look_at(eye, (0.0, 0.0, 0.0)), near=0.05)


def textured_model(n: int = 80, seed: int = 0, sh_degree: int = 3, max_res: int = 9,
                   texture_mode: str = "content_aware") -> SurfelModel:
    """n overlapping tilted surfels around the origin with strong textures (texel offsets up to +-0.9)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    res = torch.randint(1, max_res + 1, (n, 2), generator=g, dtype=torch.int32)
    res[torch.arange(n) % 9 == 4] = 0  # some surfels without texture
    scales = 0.05 + 0.25 * r(n, 2)
    # content-aware: texel size k = k_min * 2^e, chosen so the grid spans about +-2.5 sigma
    k = (5.0 * scales.max(1).values / res.clamp_min(1).max(1).values.float())
    e = torch.zeros(n, dtype=torch.int32)
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.15
    sh[:, 0] += 0.2
    t = int((res[:, 0].long() * res[:, 1].long()).sum())
    return SurfelModel(
        means=(r(n, 3) - 0.5) * torch.tensor([2.4, 1.8, 1.2]),
        log_scales=scales.log(),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g) * 1.5 + 1.0,
        sh=sh,
        textures_raw=torch.randn(t, 3, generator=g) * 1.5,
        k_min=k, t2p_exp=e, tex_res=res, tex_offset=jagged_offsets(res),
        sh_degree=sh_degree, texture_mode=texture_mode,
    )


def psnr(a, b) -> float:
    """PSNR in dB of two images in [0, 1] (any array-likes of equal shape)."""
    a, b = torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)
