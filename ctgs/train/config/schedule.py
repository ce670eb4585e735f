"""What happens at which iteration: learning rates, tau_tr, SH degree, routine calendar.

Every iteration count in the config is at the paper's scale (30k iterations) and is a fraction of the run:
`at(cfg, n)` = n x cfg.iterations / 30000 (or x cfg.schedule_scale when that expert override is > 0).
Periodic events fire when a multiple of their (fractional) period falls in (it - 1 + shift, it + shift]. With a
fixed length shift = 0: the plain `it % period == 0` calendar. A `--time-budget` run re-plans cfg.iterations while
it runs, which rescales every period; its planner then moves `shift` so that the phase (it + shift) / period is
continuous across the re-plan (ctgs.train.components.budget.BudgetPlanner.shift). Without it (as before the shift
existed) a re-plan moved the calendar's grid under the current iteration: on a `make demo` run 7 of 29 gaps between
full routines were under half a period (10-95 iterations) and 7 over 1.5 periods (up to 3); after, 0.96-1.03
(benchmarks/results/archive/routine_spacing/80dacd2.md).
"""

from __future__ import annotations

import math

import torch

from ctgs.train.config import TrainConfig

PAPER_ITERATIONS = 30000
_EPS = 1e-9  # float periods like 250 * 0.12 must still fire at their integer multiples


def factor(cfg: TrainConfig) -> float:
    """This run's iterations per paper iteration."""
    return cfg.schedule_scale if cfg.schedule_scale > 0 else cfg.iterations / PAPER_ITERATIONS


def at(cfg: TrainConfig, paper_iterations: float) -> float:
    """A paper-scale iteration count -> this run's (not rounded)."""
    return paper_iterations * factor(cfg)


def at_int(cfg: TrainConfig, paper_iterations: float) -> int:
    """`at`, rounded, at least 1 (a start iteration or a window bound)."""
    return max(1, int(round(at(cfg, paper_iterations))))


def every(cfg: TrainConfig, paper_period: float, it: int, shift: float = 0.0) -> bool:
    """True if a multiple of the scaled period lies in (it - 1 + shift, it + shift] (every iteration if the period
    <= 1). shift: the calendar's phase shift of a re-planned run (module docstring); 0 for a fixed length."""
    if paper_period <= 0:
        return False
    period = at(cfg, paper_period)
    if period <= 1:
        return True
    # it + 0.0 is it exactly, so a fixed-length run (shift 0) gets the plain calendar bit for bit.
    return math.floor((it + shift) / period + _EPS) > math.floor((it - 1 + shift) / period + _EPS)


def _log_lerp(a: float, b: float, t: float) -> float:
    """Exponential decay from a (t = 0) to b (t = 1)."""
    return math.exp(math.log(a) * (1 - t) + math.log(b) * t)


def position_lr(cfg: TrainConfig, it: int, extent: float) -> float:
    """3DGS exponential decay from lr_position_init to lr_position_final (x scene extent, world units)."""
    t = min(max(it / max(cfg.iterations, 1), 0.0), 1.0)
    return _log_lerp(cfg.lr_position_init, cfg.lr_position_final, t) * extent


def tau_tr(cfg: TrainConfig, it: int) -> float:
    """Split threshold (texels): linear from tau_tr_start to tau_tr_end over tau_tr_iters, then constant."""
    t = min(it / max(at(cfg, cfg.tau_tr_iters), 1e-9), 1.0)
    return cfg.tau_tr_start + (cfg.tau_tr_end - cfg.tau_tr_start) * t


def sh_degree(cfg: TrainConfig, it: int) -> int:
    return min(cfg.max_sh_degree, int(math.floor(it / max(at(cfg, cfg.sh_every), 1e-9) + _EPS)))


def texture_start(cfg: TrainConfig) -> int:
    return at_int(cfg, cfg.texture_start)


def routine_window(cfg: TrainConfig) -> tuple[int, int]:
    """[first, last] iteration of full routines: texture start .. min(routine_until, iterations - margin)."""
    end = min(at(cfg, cfg.routine_until), cfg.iterations - at(cfg, cfg.routine_margin))
    return texture_start(cfg), int(math.floor(end + _EPS))


def replanned_shift(shift: float, it: int, old_iterations: int, new_iterations: int) -> float:
    """The calendar's phase shift after a re-plan at `it` from old to new iterations: every scaled period changes by
    new / old, and (it + shift) / period must not jump."""
    return (it + shift) * new_iterations / old_iterations - it


def routine_kind(cfg: TrainConfig, it: int, shift: float = 0.0) -> str | None:
    """'full' (E, split, up/downscale, prune, k_min), 'late' (downscale + light prune), 'late_prune' (light prune and
    k_min only) or None.

    Full routines: every routine_every from texture_start to min(routine_until, iterations - margin).
    After that, a downscale pass every late_downscale_every until the end (not at the last step), and with
    late_prune_every > 0 a light prune at its other multiples (the authors' code prunes every 250 iterations).
    """
    if cfg.method != "content_aware" or it <= 0 or it >= cfg.iterations:
        return None
    start, end = routine_window(cfg)
    if start <= it <= end and every(cfg, cfg.routine_every, it, shift):
        return "full"
    if it > max(end, start) and every(cfg, cfg.late_downscale_every, it, shift):
        return "late"
    if it > max(end, start) and cfg.late_prune_every > 0 and every(cfg, cfg.late_prune_every, it, shift):
        return "late_prune"
    return None


def densify_stretch(cfg: TrainConfig) -> float:
    """How much a short run spaces its densifications out (>= 1): densify_every scaled to the run is at least
    densify_min_steps steps. Scaled like every other period, the paper's 145 densifications in 30k steps came every 4
    steps of a 1,055-step budgeted run (Deep Blending playroom at 158x104, 10 minutes): each averaged the gradients of
    4 views and the model had 4 steps to answer the last, so every one cloned the same regions again and the count
    grew from 15.9k to 760k. The window (densify_from..densify_until) keeps its fraction of the run; the opacity
    resets stretch alike, keeping their ratio to the densifications."""
    period = at(cfg, cfg.densify_every)
    if cfg.densify_min_steps <= 0 or period >= cfg.densify_min_steps:
        return 1.0
    return cfg.densify_min_steps / max(period, 1e-9)


def densify_active(cfg: TrainConfig, it: int, shift: float = 0.0) -> bool:
    """Baselines: a densification step at this iteration."""
    return (at(cfg, cfg.densify_from) < it <= at(cfg, cfg.densify_until)
            and every(cfg, cfg.densify_every * densify_stretch(cfg), it, shift))


def opacity_reset_period(cfg: TrainConfig) -> float:
    """Paper-scale iterations between the baselines' opacity resets (stretched with the densifications)."""
    return cfg.opacity_reset_every * densify_stretch(cfg)


def opacity_reset(cfg: TrainConfig, it: int, shift: float = 0.0) -> bool:
    return it <= at(cfg, cfg.densify_until) and every(cfg, opacity_reset_period(cfg), it, shift)


def content_opacity_reset(cfg: TrainConfig, it: int, shift: float = 0.0) -> bool:
    """Content-aware runs with content_opacity_reset: True at a full routine whose period (it - routine period, it]
    holds a multiple of opacity_reset_every at or before densify_until (the reset then follows that routine, so a
    whole routine period passes before the next prune). Stateless, so a resumed run resets where the whole run would."""
    if not cfg.content_opacity_reset or routine_kind(cfg, it, shift) != "full":
        return False
    reset_period, routine_period = at(cfg, cfg.opacity_reset_every), at(cfg, cfg.routine_every)  # both > 0 (validate)
    last = math.floor((it + shift) / reset_period + _EPS) * reset_period - shift  # the last multiple at or before it
    return last > 0 and last > it - max(routine_period, 1.0) + _EPS and last <= at(cfg, cfg.densify_until) + _EPS


def texture_lr(cfg: TrainConfig, it: int) -> float:
    """0 before texture_start (and for 2dgs); then lr_texture, constant (paper) or, with lr_texture_final > 0,
    decaying exponentially to lr_texture_final at the last iteration."""
    start = texture_start(cfg)
    if cfg.method == "2dgs" or it < start:
        return 0.0
    if cfg.lr_texture_final <= 0:
        return cfg.lr_texture
    t = min((it - start) / max(cfg.iterations - start, 1), 1.0)
    return _log_lerp(cfg.lr_texture, cfg.lr_texture_final, t)


def scale_lr(cfg: TrainConfig, it: int) -> float:
    """lr_scale, constant (paper) or, with lr_scale_final > 0, decaying exponentially from iteration 0 to
    lr_scale_final at the last iteration."""
    if cfg.lr_scale_final <= 0:
        return cfg.lr_scale
    t = min(it / max(cfg.iterations, 1), 1.0)
    return _log_lerp(cfg.lr_scale, cfg.lr_scale_final, t)


def learning_rates(cfg: TrainConfig, it: int, extent: float, k: int, device) -> dict:
    """Per-parameter learning rates at iteration `it`; `k` = SH coefficients per channel."""
    sh_lr = torch.full((1, k, 1), cfg.lr_sh_rest, device=device)
    sh_lr[:, 0] = cfg.lr_sh_dc
    tex = texture_lr(cfg, it)
    return {
        "means": position_lr(cfg, it, extent), "log_scales": scale_lr(cfg, it), "quats": cfg.lr_rotation,
        "opacity_logits": cfg.lr_opacity, "sh": sh_lr, "textures_raw": tex,
    }
