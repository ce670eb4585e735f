"""Where a surfel reaches and how fine its texels are: the active extent (the renderer's cutoffs applied to
its opacity and scales) and the texel size, in world units. Training sizes textures by them
(ctgs.train.routines.texels), export bakes texels by them (ctgs.formats.bake)."""

from __future__ import annotations

import math

import torch

from ctgs.render.constants import CUTOFF_RHO, MIN_ALPHA

# The renderer's cutoffs: alpha < MIN_ALPHA is skipped, and nothing is drawn past rho = CUTOFF_RHO (3 sigma).
CUTOFF_SIGMA = math.sqrt(CUTOFF_RHO)


def active_half_extent(model) -> torch.Tensor:
    """[N, 2] half extent (world units) where the surfel can reach alpha >= 1/255: the official code's
    sqrt(2 ln(255 o)) sigma, capped at 3 sigma (0 if the opacity can never reach 1/255)."""
    o = model.opacities.detach()
    r = torch.sqrt(2 * torch.log((o / MIN_ALPHA).clamp_min(1.0))).clamp(max=CUTOFF_SIGMA)  # [N] sigmas
    return r[:, None] * model.scales.detach()


def texel_size(model) -> torch.Tensor:
    """[N] world units per texel (content-aware mode: isotropic)."""
    return model.k_min * torch.pow(2.0, model.t2p_exp.to(model.k_min.dtype))


def active_resolution(model) -> torch.Tensor:
    """[N, 2] texels across the active extent on each axis (not rounded)."""
    return 2 * active_half_extent(model) / texel_size(model)[:, None]


def active_texels(model) -> int:
    """Texels inside the active extents: per textured primitive ceil(active_resolution) on each axis, at least 1 and at
    most its allocation. The authors' code crops every texture to this size when it saves a model
    (`_calculate_active_texture_resolution`), so the paper's texel counts are of this kind; `num_texels` counts the
    allocation (rounded up to a power of two or a multiple of 4 while training)."""
    if model.num_primitives == 0 or model.num_texels == 0:
        return 0
    res = model.tex_res.to(torch.long)
    act = torch.ceil(active_resolution(model)).to(torch.long)
    act = torch.minimum(act.clamp_min(1), res)
    return int(act.prod(1).sum())
