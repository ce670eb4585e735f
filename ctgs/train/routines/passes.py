"""The texel-size adaptation and primitive management routine (paper algorithm 1) in one place."""

from __future__ import annotations

import torch

from ctgs.train.config import schedule
from ctgs.train.routines import size_budget, texels
from ctgs.train.routines.error import compute_E, top_fraction_mask
from ctgs.train.routines.kmin import compute_k_min
from ctgs.train.routines.split import prune, split


def error_views(views, cfg, it: int) -> list:
    """The training views E is computed over at the routine of iteration `it`: all of them, or cfg.error_views drawn
    at random without replacement (seeded by the run's seed and the iteration, so a resumed run draws the same)."""
    if cfg.error_views <= 0 or len(views) <= cfg.error_views:
        return list(views)
    gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + it)
    pick = torch.randperm(len(views), generator=gen)[: cfg.error_views].sort().values
    return [views[i] for i in pick.tolist()]


def upscale_after_split(model, E: torch.Tensor, children: torch.Tensor, cfg, far: torch.Tensor | None) -> torch.Tensor:
    """[N] bool: the upscale set as the authors' code chooses it, after the split: E (children of this split at 0,
    as it zeroes theirs) times [texture can be upscaled], strictly above its (1 - top_fraction) quantile over every
    primitive (every one but the `far` ones, which are never upscaled), and > 0. With cfg.upscale_split_children the
    children keep their E."""
    E = E.clone()
    if not cfg.upscale_split_children:
        E[children] = 0
    E = E * texels.upscale_selection(model, torch.ones_like(children), cfg.min_t2p_exp).to(E.dtype)
    return _top_fraction(E, cfg.top_fraction, far)


def _top_fraction(E: torch.Tensor, fraction: float, far: torch.Tensor | None) -> torch.Tensor:
    """[N] bool: top_fraction_mask of E, taken among the primitives that are not `far` (never chosen) where given."""
    if far is None:
        return top_fraction_mask(E, fraction)
    top = torch.zeros_like(far)
    top[~far] = top_fraction_mask(E[~far], fraction)
    return top


@torch.no_grad()
def full_routine(model, opt, cfg, it: int, views, render_fn, cameras, background=None, lean: bool = True,
                 gains=None, step_errors=None) -> dict:
    """E over the training views (all, or cfg.error_views of them); split (tau_tr), upscale top E (t2p_exp > min),
    downscale the others (E_d < tau_ds); prune; k_min; reallocate. Returns statistics for the log.

    The upscale set: with cfg.upscale_after_split (the authors' code) the top fraction of E over every primitive
    after the split, among those whose texture can be upscaled (upscale_after_split); otherwise the split's
    candidates (the top fraction of E before it) that are left and can be upscaled.

    background: optional function model -> [N] bool of primitives the ranking leaves out (never split or upscaled;
    the top fraction is taken among the others).
    gains: {view name: gain} for E (compute_E; exposure_in_E), or None.
    lean=False: upscale first, to 2x, then downscale, and let realloc crop (the paper's order; the same final state
    with up to ~2x the texels in between: tests/train/test_routines_image.py, benchmarks/results/archive/lean_routine/).
    step_errors: E (and its support) from the training steps since the last routine (error.StepErrors), when they
    cover the model's primitives; otherwise E is rendered over `views`.
    """
    support = None
    from_steps = step_errors is not None and step_errors.covers(model.num_primitives)
    if from_steps:
        E, support = step_errors.E(), (step_errors.support if cfg.max_params > 0 else None)
    elif cfg.max_params > 0:
        E, support = compute_E(model, error_views(views, cfg, it), render_fn, cfg.lambda_ssim, with_support=True,
                               gains=gains)
    else:
        E = compute_E(model, error_views(views, cfg, it), render_fn, cfg.lambda_ssim, gains=gains)
    top = _top_fraction(E, cfg.top_fraction, None if background is None else background(model))
    n0 = model.num_primitives
    # carried through the split (children inherit the parent's): E for an upscale set chosen after it, and support
    cols = ([E] if cfg.upscale_after_split else []) + ([support] if support is not None else [])
    carry = torch.stack([c.to(E.dtype) for c in cols], 1) if cols else None
    children = []
    out = split(model, opt, top, schedule.tau_tr(cfg, it), cfg.max_primitives, priority=E, carry=carry,
                children_stay=cfg.upscale_split_children, fresh_children=cfg.split_fresh_moments,
                scale_cap=cfg.split_scale_cap, children_out=children, truncate=cfg.split_offset_truncated)
    n_split, top = out[0], out[1]
    if carry is not None:
        carry = out[2]
        if support is not None:
            support = carry[:, -1]
    if cfg.upscale_after_split:
        top = upscale_after_split(model, carry[:, 0], children[0], cfg,
                                  None if background is None else background(model))
    if lean:
        # The same result as upscaling first (the two touch disjoint primitives, each texture alone), with the
        # textures at their smallest in between: downscale the others first, then upscale cropped as made to what
        # realloc below gives it, so that 4x the upscaled texels never exist at once.
        up = texels.upscale_selection(model, top, cfg.min_t2p_exp)
        down, e_d = texels.downscale(model, opt, ~up, cfg.tau_ds, thin=cfg.downscale_thin,
                                      fresh_moments=cfg.texture_fresh_moments, corners=cfg.downscale_corners)
        texels.upscale(model, opt, up, cfg.min_t2p_exp,
                       crop=(cameras, cfg.max_texture_res, cfg.texture_alloc, cfg.texture_sigma),
                       fresh_moments=cfg.texture_fresh_moments)
    else:
        up = texels.upscale(model, opt, top, cfg.min_t2p_exp, fresh_moments=cfg.texture_fresh_moments)
        down, e_d = texels.downscale(model, opt, ~up, cfg.tau_ds, thin=cfg.downscale_thin,
                                      fresh_moments=cfg.texture_fresh_moments, corners=cfg.downscale_corners)
    kept = model.opacities.detach() >= cfg.prune_opacity  # what prune keeps (support and up follow it)
    n_pruned = prune(model, opt, cfg.prune_opacity)
    model.k_min = compute_k_min(model.means.detach(), cameras)
    texels.realloc(model, opt, cfg.max_texture_res, cfg.texture_alloc, cfg.texture_sigma,
                   fresh_moments=cfg.texture_fresh_moments)
    # --max-params: what was just upscaled stays; the rest is coarsened where that loses least (size_budget)
    budget = size_budget.fit(model, opt, cfg, keep=up[kept], support=None if support is None else support[kept])
    return {"E_mean": float(E.mean()) if E.numel() else 0.0, "E_p90": float(E.quantile(0.9)) if E.numel() else 0.0,
            "tau_tr": schedule.tau_tr(cfg, it), "n_before": n0, "split": n_split, "upscaled": int(up.sum()),
            "downscaled": int(down.sum()), "pruned": n_pruned, "E_steps": step_errors.steps if from_steps else 0,
            **(budget or {})}


@torch.no_grad()
def late_routine(model, opt, cfg, cameras) -> dict:
    """After the main phase: downscale everything that passes, light pruning, k_min, reallocate."""
    down, _ = texels.downscale(model, opt, torch.ones(model.num_primitives, dtype=torch.bool,
                                                         device=model.means.device), cfg.tau_ds,
                               thin=cfg.downscale_thin, fresh_moments=cfg.texture_fresh_moments,
                               corners=cfg.downscale_corners)
    n_pruned = prune(model, opt, cfg.prune_opacity_late)
    model.k_min = compute_k_min(model.means.detach(), cameras)
    texels.realloc(model, opt, cfg.max_texture_res, cfg.texture_alloc, cfg.texture_sigma,
                   fresh_moments=cfg.texture_fresh_moments)
    budget = size_budget.fit(model, opt, cfg)
    return {"downscaled": int(down.sum()), "pruned": n_pruned, **(budget or {})}


@torch.no_grad()
def late_prune(model, opt, cfg, cameras) -> dict:
    """Between the late downscales (late_prune_every): prune below prune_opacity_late and update k_min, as the authors'
    code does every 250 iterations after its routines end."""
    n_pruned = prune(model, opt, cfg.prune_opacity_late)
    model.k_min = compute_k_min(model.means.detach(), cameras)
    return {"pruned": n_pruned}
