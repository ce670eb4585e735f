"""Pinhole camera, the one convention used everywhere in ctgs.

COLMAP/OpenCV convention: camera looks down +z, x right, y down; the centre of pixel (i, j) (column i,
row j) is at continuous image coordinates (i + 0.5, j + 0.5). `viewmat` maps world -> camera.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch


@dataclass(frozen=True)
class Camera:
    fx: float  # focal length, pixels
    fy: float
    cx: float  # principal point, pixels (continuous image coordinates)
    cy: float
    width: int  # W
    height: int  # H
    viewmat: torch.Tensor  # [4, 4] world -> camera, float32 (or float64), CPU or CUDA
    near: float = 0.01  # world units: intersections closer than this are ignored (load_scene: 1e-3 x extent)

    @property
    def R(self) -> torch.Tensor:  # [3, 3] world -> camera rotation
        return self.viewmat[:3, :3]

    @property
    def t(self) -> torch.Tensor:  # [3]
        return self.viewmat[:3, 3]

    @property
    def center(self) -> torch.Tensor:  # [3] camera centre in world coordinates
        return -self.R.transpose(0, 1) @ self.t

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """World points [N, 3] -> pixel coordinates u, v (continuous), camera-space depth z, each [N], and `inside`
        [N] bool: in front of the near plane and on the image. Computed in the points' dtype and device."""
        vm = self.viewmat.detach().to(device=points.device, dtype=points.dtype)
        pc = points @ vm[:3, :3].T + vm[:3, 3]
        z = pc[:, 2]
        u = self.fx * pc[:, 0] / z.clamp_min(1e-9) + self.cx
        v = self.fy * pc[:, 1] / z.clamp_min(1e-9) + self.cy
        inside = (z > self.near) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        return u, v, z, inside

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (e.g. 0.5 for images_2)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=w, height=h)

    def to(self, device: torch.device | str, dtype: torch.dtype | None = None) -> "Camera":
        return replace(self, viewmat=self.viewmat.to(device=device, dtype=dtype or self.viewmat.dtype))
