"""init_shell's far primitives: those beyond a sphere around the reconstructed scene (the shell's, and anything that
drifted as far). The shell component (ctgs.train.components.shell) draws the sphere; the split and upscale ranking
leaves what lies beyond it out."""

from __future__ import annotations

import numpy as np
import torch

# Primitives farther than this many times the reach from the centre count as background: between the reconstructed
# scene (<= 1x) and the shell (3x).
FAR_FACTOR = 2.0


def far_mask(means: torch.Tensor, centre: np.ndarray, reach: float) -> torch.Tensor:
    """[N] bool tensor: primitives beyond FAR_FACTOR x reach from the centre."""
    c = torch.as_tensor(centre, dtype=means.dtype, device=means.device)
    return (means.detach() - c).norm(dim=1) > FAR_FACTOR * reach
