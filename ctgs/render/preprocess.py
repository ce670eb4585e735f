"""Differentiable per-primitive preprocessing for the extension backends (docs/reference/renderer.md, "Per primitive"):
world -> camera space and SH -> colour, in PyTorch so autograd carries the kernels' camera-space gradients
back to means, quats and SH."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ctgs.ops.dispatch import fusable_here
from ctgs.render.camera import Camera
from ctgs.render.geometry import quat_to_rotmat
from ctgs.render.sh import view_color


@dataclass
class CameraSpacePrims:
    """What the kernels consume (all [N, ...], dtype of the means)."""

    mu_c: torch.Tensor  # [N, 3] centres, camera space, world units
    Rc: torch.Tensor  # [N, 3, 3] camera-space rotation, columns tangent u, tangent v, normal
    colors: torch.Tensor  # [N, 3] SH(view dir) + 0.5, unclamped


class _CameraSpace(torch.autograd.Function):
    """(mu_c, Rc) of camera_space_torch in one compiled pass each way (kernels/include/ctgs/preprocess.h:
    kernels/cpu/camera.cpp on the CPU, kernels/cuda/dense.cu on a GPU)."""

    @staticmethod
    def forward(ctx, means, quats, view):
        ctx.save_for_backward(quats, view)
        return tuple(torch.ops.ctgs.camera_space(means, quats, view, torch.get_num_threads()))

    @staticmethod
    def backward(ctx, grad_mu_c, grad_Rc):
        quats, view = ctx.saved_tensors
        n = quats.shape[0]
        grad_mu_c = quats.new_zeros(n, 3) if grad_mu_c is None else grad_mu_c.contiguous()
        grad_Rc = quats.new_zeros(n, 3, 3) if grad_Rc is None else grad_Rc.contiguous()
        gm, gq = torch.ops.ctgs.camera_space_backward(quats, view, grad_mu_c, grad_Rc, torch.get_num_threads())
        return (gm if ctx.needs_input_grad[0] else None), (gq if ctx.needs_input_grad[1] else None), None


def camera_space_torch(means: torch.Tensor, quats: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """mu_c [N, 3] = R mean + t, Rc [N, 3, 3] = R quat_to_rotmat(quat) for view = [R t] (PyTorch)."""
    rv, tv = view[:3, :3], view[:3, 3]  # [3, 3], [3]
    return means @ rv.T + tv, rv @ quat_to_rotmat(quats)


def camera_space(means: torch.Tensor, quats: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """camera_space_torch in one compiled pass each way, on the CPU and on a GPU (differentiable w.r.t. means
    and quats, not the view; the same values to float rounding: tests/render/test_preprocess.py,
    tests/render/test_cuda_backend.py)."""
    if (not view.requires_grad and means.ndim == 2 and means.shape[1] == 3 and quats.ndim == 2
            and quats.shape[1] == 4 and quats.shape[0] == means.shape[0] and quats.dtype == means.dtype
            and view.dtype == means.dtype and view.device == means.device == quats.device):
        m, q, v = means.contiguous(), quats.contiguous(), view.detach().contiguous()
        if fusable_here(m, q, v):
            mu_c, Rc = _CameraSpace.apply(m, q, v)
            return mu_c, Rc
    return camera_space_torch(means, quats, view)


def to_camera_space(means: torch.Tensor, quats: torch.Tensor, sh: torch.Tensor, camera: Camera,
                    sh_degree: int) -> CameraSpacePrims:
    view = camera.viewmat.to(device=means.device, dtype=means.dtype)
    rv, tv = view[:3, :3], view[:3, 3]  # [3, 3], [3]
    mu_c, Rc = camera_space(means, quats, view)
    center = -rv.T @ tv  # [3] camera centre, world
    colors = view_color(means, sh, center, sh_degree)
    return CameraSpacePrims(mu_c=mu_c, Rc=Rc, colors=colors)
