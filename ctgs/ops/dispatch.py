"""Which compiled extension serves tensors on a device: the per-primitive kernels (camera space, SH colour)
exist on the CPU (ctgs.ops.fused's extension) and on a GPU (ctgs.ops.ext_cuda)."""

from __future__ import annotations

import torch

from ctgs.ops.ext_cuda import cuda_fusable, load_cuda
from ctgs.ops.fused import cpu_ext, fusable


def compiled(device: torch.device):
    """The compiled extension holding the per-primitive kernels for tensors on `device` and its name suffix:
    (module, "cpu") or (module, "cuda")."""
    if device.type == "cuda":
        return load_cuda(), "cuda"
    return cpu_ext(), "cpu"


def fusable_here(*tensors: torch.Tensor) -> bool:
    """Whether the compiled per-primitive kernels apply: contiguous float CPU tensors with the CPU extension
    (ctgs.ops.fused.fusable), or contiguous float CUDA tensors with the CUDA extension."""
    if tensors and tensors[0].is_cuda:
        return cuda_fusable(*tensors)
    return fusable(*tensors)
