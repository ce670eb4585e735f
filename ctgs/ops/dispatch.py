"""Which compiled kernels apply to a tensor's device. The ops themselves are declared in ctgs.ops.schemas and
called as `torch.ops.ctgs.<op>(...)`: the dispatcher runs the kernel of the tensors' device."""

from __future__ import annotations

import torch

from ctgs.ops.ext_cuda import cuda_fusable
from ctgs.ops.fused import fusable


def fusable_here(*tensors: torch.Tensor) -> bool:
    """Whether the compiled per-primitive kernels apply: contiguous float CPU tensors with the CPU extension
    (ctgs.ops.fused.fusable), or contiguous float CUDA tensors with the CUDA extension; either is loaded here."""
    if tensors and tensors[0].is_cuda:
        return cuda_fusable(*tensors)
    return fusable(*tensors)
