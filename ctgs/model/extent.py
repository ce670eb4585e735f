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


def active_texels(model, cap: int = 256) -> int:
    """Texels of the textures as the authors' code saves a model (`save_texture_maps`: each texture cropped tight to
    its active extent, `_calculate_active_texture_resolution`): per textured primitive and axis, with e =
    ceil(active_resolution), e + 2 texels if e is even and e + 1 if odd (the texels centred on the surfel that cover
    e), at most `cap` (the authors' maximum resolution). The paper's texel counts are of this kind; `num_texels`
    counts the allocation (rounded up to a power of two or a multiple of 4 while training)."""
    if model.num_primitives == 0 or model.num_texels == 0:
        return 0
    textured = model.tex_res.to(torch.long).prod(1) > 0
    e = torch.ceil(active_resolution(model)).to(torch.long)
    tight = torch.where(e % 2 == 0, e + 2, e + 1).clamp(1, cap)
    return int(tight[textured].prod(1).sum())
