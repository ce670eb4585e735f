"""`--max-params N`: a size budget for the trained model (parameters as SurfelModel.num_params counts them).

Where the parameters go: a primitive holds a fixed count (59 at SH degree 3, fewer at lower degrees), a texel 3.
The budget is kept two ways:
- primitives: splits (content-aware) and densification (baselines) stop at the count whose parameters, with the
  smallest texture each can have (2x2 texels; the fixed_texture baseline's fixed grid), fill the budget
  (`primitive_cap`, folded into max_primitives by rules.resolve);
- texels: after every routine, reallocation and at the end, textures are coarsened where that loses least until the
  texels fit what the primitives leave (texels.fit_texels). Counted as the final trim will leave them, so the
  padding it drops does not use up the budget; at the end (after the trim) counted exactly, so the model written
  holds at most N parameters, or the run says by how much it could not.
"""

from __future__ import annotations

import torch

from ctgs.model import surfels
from ctgs.train.routines import texels

MIN_TEXELS = 4  # 2x2: the smallest texture a content-aware reallocation gives


def params_per_primitive(method: str, max_sh_degree: int) -> int:
    """SurfelModel.num_params per primitive of a `method` model (the 2dgs baseline has no texel size)."""
    return surfels.params_per_primitive(max_sh_degree, textured=method != "2dgs")


def primitive_cap(method: str, max_sh_degree: int, max_params: int, fixed_texture_res: int = 16) -> int:
    """Most primitives a budget of max_params can hold (0 = no budget): each with its own parameters and the
    smallest texture it can have."""
    if max_params <= 0:
        return 0
    tex = {"2dgs": 0, "fixed_texture": fixed_texture_res ** 2}.get(method, MIN_TEXELS)
    return max(1, max_params // (params_per_primitive(method, max_sh_degree) + 3 * tex))


def texel_budget(model, max_params: int) -> int:
    """Texels the budget leaves once the model's primitives are paid for (may be negative: over already)."""
    per_prim = model.num_params() - 3 * model.num_texels
    return (max_params - per_prim) // 3


@torch.no_grad()
def fit(model, opt, cfg, keep: torch.Tensor | None = None, support: torch.Tensor | None = None,
        final: bool = False) -> dict | None:
    """Coarsen textures until the model fits cfg.max_params (content-aware runs with a budget; None otherwise or when
    it already fits). final: after the trim, exact counts, no reallocation."""
    if cfg.max_params <= 0 or model.texture_mode != "content_aware" or model.num_texels == 0:
        return None
    if model.num_params() <= cfg.max_params:
        return None
    budget = texel_budget(model, cfg.max_params)
    trim_eps = 0.0 if final else cfg.texture_trim
    stats = None
    # `keep` first (just upscaled: the others pay for them); if they cannot, every texture is a candidate
    for k in ((keep, None) if keep is not None else (None,)):
        got = texels.fit_texels(model, opt, max(budget, 0), cfg.max_texture_res, cfg.texture_alloc,
                                cfg.texture_sigma, keep=k, support=support, trim_eps=trim_eps, reallocate=not final)
        n = got["budget_downscaled"] + (stats["budget_downscaled"] if stats else 0)
        stats = {**got, "budget_downscaled": n}
        if got["budget_texels"] <= budget:
            break
    if stats["budget_downscaled"] == 0 and stats["budget_texels"] <= budget:
        return None
    return {**stats, "texel_budget": int(budget)}
