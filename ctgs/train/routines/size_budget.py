"""`--max-params N`: a size budget for the trained model (parameters as SurfelModel.num_params counts them).

Where the parameters go: a primitive holds a fixed count (59 at SH degree 3, fewer at lower degrees), a texel 3.
The budget is kept two ways:
- primitives: splits (content-aware) and densification (baselines) stop at the count whose parameters, with the
  smallest texture each can have (2x2 texels; the fixed_texture baseline's fixed grid), fill the budget
  (ctgs.train.config.rules.primitive_cap, folded into max_primitives by rules.resolve);
- texels: after every routine, reallocation and at the end, textures are coarsened where that loses least until the
  texels fit what the primitives leave (texels.fit_texels). Counted as the final trim will leave them, so the
  padding it drops does not use up the budget; at the end (after the trim) counted exactly, so the model written
  holds at most N parameters, or the run says by how much it could not.
"""

from __future__ import annotations

import torch

from ctgs.train.routines import texels


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
