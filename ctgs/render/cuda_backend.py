"""The CUDA backend behind `render(..., backend="cuda")`: device checks, then the shared autograd
bridge (ctgs.render.rasterize) with the kernels of kernels/cuda. Semantics: docs/reference/renderer.md.
"""

from __future__ import annotations

import torch

from ctgs.ops.ext_cuda import load_cuda
from ctgs.render.camera import Camera
from ctgs.render.rasterize import rasterize
from ctgs.render.types import RenderOutput, SurfelInputs


def render_cuda(s: SurfelInputs, camera: Camera, sh_degree: int, background: torch.Tensor,
                error_image: torch.Tensor | None, poison: bool = False) -> RenderOutput:
    """Validated inputs on one CUDA device -> RenderOutput (see ctgs.render.render)."""
    load_cuda()  # no GPU or no toolkit: a one-line UserError before anything else
    if not s.means.is_cuda:
        raise ValueError(f"the cuda backend needs CUDA tensors (means is on {s.means.device}); move the surfels "
                         "with .to('cuda') or pass backend='auto'")
    return rasterize(s, camera, sh_degree, background, error_image, device="cuda", knob=0, poison=poison)
