"""What happens at which iteration: learning rates, tau_tr, SH degree, routine calendar.

All iteration counts in the config are at the paper's scale and pass through `cfg.scaled`.
"""

from __future__ import annotations

import math

import torch

from ctgs.train.config import TrainConfig


def position_lr(cfg: TrainConfig, it: int, extent: float) -> float:
    """3DGS exponential decay from lr_position_init to lr_position_final (x scene extent, world units)."""
    t = min(max(it / max(cfg.iterations, 1), 0.0), 1.0)
    lr = math.exp(math.log(cfg.lr_position_init) * (1 - t) + math.log(cfg.lr_position_final) * t)
    return lr * extent


def tau_tr(cfg: TrainConfig, it: int) -> float:
    """Split threshold (texels): linear from tau_tr_start to tau_tr_end over tau_tr_iters, then constant."""
    t = min(it / cfg.scaled(cfg.tau_tr_iters), 1.0)
    return cfg.tau_tr_start + (cfg.tau_tr_end - cfg.tau_tr_start) * t


def sh_degree(cfg: TrainConfig, it: int) -> int:
    return min(cfg.max_sh_degree, it // cfg.scaled(cfg.sh_every))


def texture_start(cfg: TrainConfig) -> int:
    return cfg.scaled(cfg.texture_start)


def routine_kind(cfg: TrainConfig, it: int) -> str | None:
    """'full' (E, split, up/downscale, prune, k_min), 'late' (downscale + light prune) or None.

    Full routines: every routine_every from texture_start to min(routine_until, iterations - margin).
    After that, a downscale-only pass every late_downscale_every until the end (not at the last step).
    """
    if cfg.method != "content_aware" or it <= 0 or it >= cfg.iterations:
        return None
    start = texture_start(cfg)
    end = min(cfg.scaled(cfg.routine_until), cfg.iterations - cfg.scaled(cfg.routine_margin))
    if start <= it <= end and it % cfg.scaled(cfg.routine_every) == 0:
        return "full"
    if it > max(end, start) and it % cfg.scaled(cfg.late_downscale_every) == 0:
        return "late"
    return None


def texture_lr(cfg: TrainConfig, it: int) -> float:
    """0 before texture_start (and for 2dgs); then lr_texture, constant (paper) or, with lr_texture_final > 0,
    decaying exponentially to lr_texture_final at the last iteration."""
    start = texture_start(cfg)
    if cfg.method == "2dgs" or it < start:
        return 0.0
    if cfg.lr_texture_final <= 0:
        return cfg.lr_texture
    t = min((it - start) / max(cfg.iterations - start, 1), 1.0)
    return math.exp(math.log(cfg.lr_texture) * (1 - t) + math.log(cfg.lr_texture_final) * t)


def learning_rates(cfg: TrainConfig, it: int, extent: float, k: int, device) -> dict:
    """Per-parameter learning rates at iteration `it`; `k` = SH coefficients per channel."""
    sh_lr = torch.full((1, k, 1), cfg.lr_sh_rest, device=device)
    sh_lr[:, 0] = cfg.lr_sh_dc
    tex = texture_lr(cfg, it)
    return {
        "means": position_lr(cfg, it, extent), "log_scales": cfg.lr_scale, "quats": cfg.lr_rotation,
        "opacity_logits": cfg.lr_opacity, "sh": sh_lr, "textures_raw": tex,
    }
