"""Differentiable renderer for textured 2D Gaussian surfels.

`render(surfels, camera, backend=...)` is the one entry point; backends: "reference" (pure PyTorch,
dense, autograd), "cpu" (C++/OpenMP extension), "cuda" (CUDA extension), "auto" (cuda if the inputs
live on a GPU, else cpu). The exact semantics are in docs/reference/renderer.md.
"""

from ctgs.render.api import render
from ctgs.render.camera import Camera
from ctgs.render.types import BackwardStats, ErrorStats, RenderOutput, SurfelInputs

__all__ = ["BackwardStats", "Camera", "ErrorStats", "RenderOutput", "SurfelInputs", "render"]
