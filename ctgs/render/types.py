"""Typed inputs and outputs of the renderer (see docs/reference/renderer.md for the exact definition)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class SurfelInputs:
    """Activated per-primitive quantities, world units. Letters: N primitives, T texels, K SH coeffs."""

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4] (w, x, y, z), normalised inside the renderer
    scales: torch.Tensor  # [N, 2] standard deviations along tangent u, v (world units, > 0)
    opacities: torch.Tensor  # [N] in [0, 1]
    sh: torch.Tensor  # [N, K, 3], K in {1, 4, 9, 16}
    texel_size: torch.Tensor  # [N] or [N, 2] world units per texel along (u, v)
    textures: torch.Tensor  # [T, 3] activated texel offsets (jagged, flat)
    tex_res: torch.Tensor  # [N, 2] int32 (res_u, res_v); (0, 0) = no texture
    tex_offset: torch.Tensor  # [N] int64 start row of each primitive in `textures`

    @property
    def num_primitives(self) -> int:
        return int(self.means.shape[0])


@dataclass
class ErrorStats:
    """Per-primitive error statistics for one view (forward only; used by training routines)."""

    count: torch.Tensor  # [N] int32 pixels where the primitive was blended
    contrib: torch.Tensor  # [N] sum over those pixels of w = alpha * T
    err: torch.Tensor  # [N] sum over those pixels of e * w


@dataclass
class BackwardStats:
    """Error statistics from a CPU render's backward (render(..., backward_stats=...)): the caller sets `error_image`
    [H, W] (an error of this very render, e.g. the training loss's) before the backward runs; the backward then also
    sums, per primitive, w and e w over the pixels it blended (as a forward given that error image would: the same
    pairs, w up to rounding) into `contrib` and `err` [N]. Without an error image, or on another backend, they stay
    None."""

    error_image: torch.Tensor | None = None
    contrib: torch.Tensor | None = None
    err: torch.Tensor | None = None


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # [H, W, 3]
    alpha: torch.Tensor  # [H, W] = 1 - final transmittance
    depth: torch.Tensor  # [H, W] alpha-weighted sum of hit depths (divide by alpha for expected depth)
    stats: ErrorStats | None = None  # only when an error image was passed
    # [H, W] the median depth: the hit depth of the last surfel blended while the transmittance in front of it was
    # above 0.5 (2DGS's), 0 where nothing blended; no gradient. None where a render path does not compute it.
    median_depth: torch.Tensor | None = None
    # [H, W] alpha-weighted sum of squared hit depths, differentiable: with alpha and depth it gives the depth
    # distortion sum_ij w_i w_j (z_i - z_j)^2 = 2 (alpha depth2 - depth^2) (ctgs.train.components.normal).
    depth2: torch.Tensor | None = None
    # [N] bool: the primitives the compiled backends' binning put in a tile list for this view (what they
    # rasterize; the training loss's texture term regularises these, ctgs.train.step.loss). None elsewhere.
    rasterized: torch.Tensor | None = None
