"""The compiled ops both backends have, declared once: each op's name and schema here (torch.library), its kernels
registered by the extension of each device (TORCH_LIBRARY_IMPL: kernels/bindings.cpp for the CPU,
kernels/bindings_cuda.cpp for CUDA). `torch.ops.ctgs.<op>(...)` runs the kernel of its tensors' device, once that
device's extension is loaded: `fusable_here` loads it, and says whether the kernels apply."""

from __future__ import annotations

import torch

from ctgs.ops.ext_cuda import cuda_fusable
from ctgs.ops.fused import fusable

SCHEMAS = (
    # {mu_c [N, 3], Rc [N, 3, 3]}: world -> camera space of the means and quaternions for view [4, 4]
    "camera_space(Tensor means, Tensor quats, Tensor view, int num_threads) -> Tensor[]",
    # {grad_means [N, 3], grad_quats [N, 4]} of camera_space for its upstream gradients
    "camera_space_backward(Tensor quats, Tensor view, Tensor grad_mu_c, Tensor grad_Rc, int num_threads) -> Tensor[]",
    # colors [N, 3] = SH_degree(normalize(means - center)) + 0.5
    "sh_color(Tensor means, Tensor center, Tensor sh, int degree, int num_threads) -> Tensor",
    # {grad_means [N, 3], grad_sh [N, K, 3]} of sh_color for the upstream gradient grad_colors [N, 3]
    "sh_color_backward(Tensor means, Tensor center, Tensor sh, int degree, Tensor grad_colors, int num_threads)"
    " -> Tensor[]",
)

_library = torch.library.Library("ctgs", "DEF")
for _schema in SCHEMAS:
    _library.define(_schema)


def fusable_here(*tensors: torch.Tensor) -> bool:
    """Whether the compiled per-primitive kernels apply: contiguous float CPU tensors with the CPU extension
    (ctgs.ops.fused.fusable), or contiguous float CUDA tensors with the CUDA extension; either is loaded here."""
    if tensors and tensors[0].is_cuda:
        return cuda_fusable(*tensors)
    return fusable(*tensors)
