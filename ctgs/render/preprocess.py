"""Differentiable per-primitive preprocessing for the extension backends (docs/renderer.md, "Per primitive"):
world -> camera space and SH -> colour, in PyTorch so autograd carries the kernels' camera-space gradients
back to means, quats and SH."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ctgs.model.geometry import quat_to_rotmat
from ctgs.render.camera import Camera
from ctgs.render.sh import view_color


@dataclass
class CameraSpacePrims:
    """What the kernels consume (all [N, ...], dtype of the means)."""

    mu_c: torch.Tensor  # [N, 3] centres, camera space, world units
    Rc: torch.Tensor  # [N, 3, 3] camera-space rotation, columns tangent u, tangent v, normal
    colors: torch.Tensor  # [N, 3] SH(view dir) + 0.5, unclamped


def to_camera_space(means: torch.Tensor, quats: torch.Tensor, sh: torch.Tensor, camera: Camera,
                    sh_degree: int) -> CameraSpacePrims:
    view = camera.viewmat.to(device=means.device, dtype=means.dtype)
    rv, tv = view[:3, :3], view[:3, 3]  # [3, 3], [3]
    mu_c = means @ rv.T + tv  # [N, 3]
    Rc = rv @ quat_to_rotmat(quats)  # [N, 3, 3]
    center = -rv.T @ tv  # [3] camera centre, world
    colors = view_color(means, sh, center, sh_degree)
    return CameraSpacePrims(mu_c=mu_c, Rc=Rc, colors=colors)
