"""Differentiable renderer for textured 2D Gaussian surfels.

`render(surfels, camera, backend=...)` is the one entry point; backends: "reference" (pure PyTorch,
dense, autograd), "cpu" (C++/OpenMP extension), "cuda" (CUDA extension), "auto" (cuda if the inputs
live on a GPU, else cpu). The exact semantics are in docs/reference/renderer.md.
"""

from ctgs.render.camera import Camera
from ctgs.render.types import ErrorStats, RenderOutput, SurfelInputs

__all__ = ["Camera", "ErrorStats", "RenderOutput", "SurfelInputs", "render"]


def render(surfels, camera, *, backend="auto", sh_degree=None, background=None, error_image=None):
    """Render `surfels` (SurfelInputs) from `camera`.

    Args:
        backend: "auto" | "cpu" | "cuda" | "reference".
        sh_degree: active SH degree (default: the largest the K of `surfels.sh` allows).
        background: [3] colour behind everything (default black).
        error_image: optional [H, W] per-pixel error; when given, `RenderOutput.stats` holds the
            per-primitive error statistics (no gradient flows through them). May also be a function
            rgb [H, W, 3] -> [H, W] error of this very render (one pass instead of two on the cpu
            backend when no gradient is wanted; the statistics are the same).
    Returns: RenderOutput.
    """
    from ctgs.render.api import render as _render

    return _render(surfels, camera, backend=backend, sh_degree=sh_degree, background=background,
                   error_image=error_image)
