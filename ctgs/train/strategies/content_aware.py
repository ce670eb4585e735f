"""The content-aware strategy (the paper's method): textures allocated at texture_start; then on the schedule's
calendar the full routine (error E over the training views, split, texel up/downscaling, prune, reallocation:
ctgs.train.routines.passes), after the routine window the late downscale-only pass, texture reallocations in between;
after the last iteration the texture trim."""

from __future__ import annotations

from ctgs.render import BackwardStats
from ctgs.train.config import schedule
from ctgs.train.events import Routine
from ctgs.train.routines import size_budget, texels
from ctgs.train.routines.densify import RESET_OPACITY, reset_opacity
from ctgs.train.routines.error import StepErrors
from ctgs.train.routines.far import far_mask
from ctgs.train.routines.kmin import compute_k_min
from ctgs.train.routines.passes import full_routine, late_prune, late_routine
from ctgs.train.routines.split import prune
from ctgs.train.step.adam import TEX_PARAM
from ctgs.train.strategies.base import Strategy, settings_class


class ContentAware(Strategy):
    KEYS = (
        # when
        "texture_start", "routine_every", "routine_until", "routine_margin", "late_downscale_every",
        "late_prune_every", "realloc_every", "tau_tr_start", "tau_tr_end", "tau_tr_iters", "content_opacity_reset",
        "opacity_reset_every", "densify_until",
        # textures
        "start_texels", "start_exp_ceil", "min_t2p_exp", "max_texture_res", "texture_alloc", "texture_sigma",
        "texture_fresh_moments", "texture_steps_from_start", "texture_trim", "tau_ds", "downscale_thin",
        "downscale_corners",
        # E and the split
        "error_views", "error_from_steps", "exposure_in_E", "lambda_ssim", "top_fraction", "upscale_after_split",
        "upscale_split_children", "split_fresh_moments", "split_offset_truncated", "split_scale_cap", "init_shell",
        # pruning and size
        "prune_opacity", "prune_opacity_late", "prune_opacity_final", "max_primitives", "max_params",
    )
    Settings = settings_class("ContentAwareSettings", KEYS,
                              "The config keys of the content-aware method (`content_aware`).")
    texture_mode = "content_aware"
    starts_textures = True

    def __init__(self):
        self.errors = StepErrors()  # error_from_steps: E of the steps since the last full routine
        self.sink: BackwardStats | None = None  # the current step's statistics, filled by its backward
        self.sink_used = False  # whether the steps sum E (error_from_steps where it applies)

    def restore(self, st, saved: dict) -> None:
        st.textures_started = bool(saved.get("textures_started", st.it >= schedule.texture_start(st.cfg)))
        if "step_errors" in saved:  # (older checkpoints: E is rendered at the next routine)
            self.errors.load_state_dict(saved["step_errors"])

    def checkpoint(self, st) -> dict:
        return {"textures_started": st.textures_started, "step_errors": self.errors.state_dict()}

    def step_stats(self, st) -> BackwardStats | None:
        """error_from_steps on the CPU backend: what this step's backward fills (its loss's error image, summed per
        primitive); None where E is rendered at the routines (other backends, init_shell's composited renders)."""
        cfg = st.cfg
        on_cpu = st.device.type == "cpu" and cfg.backend in ("auto", "cpu")
        self.sink = BackwardStats() if cfg.error_from_steps and on_cpu and cfg.init_shell <= 0 else None
        self.sink_used = self.sink is not None
        return self.sink

    def errors_ready(self, st) -> bool:
        """error_from_steps: the steps since the last full routine hold at least as many views as a rendered E would
        (error_views, or every training view): a short plan's routine dates come every few steps, and an E of a handful
        of views ranks the primitives those views show. True where E is rendered."""
        if not self.sink_used:
            return True
        need = st.cfg.error_views if st.cfg.error_views > 0 else len(st.train_views)
        return self.errors.steps >= min(need, len(st.train_views))

    def post_backward(self, st, it: int, view) -> None:
        sink, self.sink = self.sink, None
        if sink is not None and sink.contrib is not None:
            self.errors.add(sink.contrib, sink.err, view.image_t.shape[0] * view.image_t.shape[1])

    def start_textures(self, st) -> None:
        """Allocate st.model's textures (the run's texture start; the calibration does it on its copy)."""
        cfg = st.cfg
        st.model.k_min = compute_k_min(st.model.means.detach(), st.cameras)
        texels.start_textures(st.model, st.opt, cfg.start_texels, cfg.min_t2p_exp, cfg.max_texture_res,
                              cfg.texture_alloc, cfg.texture_sigma, ceil=cfg.start_exp_ceil)
        if cfg.texture_steps_from_start:
            # torch's Adam in the authors' code counts the textures' steps from the first iteration (their learning
            # rate is 0 until the texture start): no bias correction after it, so moments restarted at zero move a
            # texel by up to several times the learning rate at first
            st.opt.steps[TEX_PARAM] = max(st.opt.steps[TEX_PARAM], st.it)

    def step_end(self, st, it: int):
        cfg, model, opt, shift = st.cfg, st.model, st.opt, st.shift
        # --time-budget: not before the plan rests on measured steps (BudgetPlanner.measured_plan)
        if not st.textures_started and it >= schedule.texture_start(cfg) and st.textures_may_start:
            st.textures_started = True
            self.start_textures(st)
            budget = size_budget.fit(model, opt, cfg)
            yield Routine(it, "texture_start", {"t2p_exp_mean": float(model.t2p_exp.float().mean()),
                                                **(budget or {})})
        # Routines refine textures: none before they start (a --time-budget run holds its texture start until
        # the plan rests on measured steps, while a short first plan's calendar may already call for routines).
        kind = schedule.routine_kind(cfg, it, shift) if st.textures_started else None
        if kind == "full" and not self.errors_ready(st):
            kind = None  # error_from_steps: E of fewer steps than E would render views waits for more
        if kind == "full" and not st.routine_kept:
            kind = None  # --time-budget: a date its routine calendar leaves out (ctgs.train.components.budget.SHARE)
        if kind == "full":
            yield Routine(it, "full", self.full_routine(st, it))
            if schedule.content_opacity_reset(cfg, it, shift):
                value = max(2.0 * cfg.prune_opacity, RESET_OPACITY)  # prune_opacity = 0 would give 0
                reset_opacity(model, opt, value)
                yield Routine(it, "opacity_reset", {"value": value})
        elif kind == "late":
            yield Routine(it, "late", late_routine(model, opt, cfg, st.cameras))
            self.errors.reset()  # (it prunes)
        elif kind == "late_prune":
            stats = late_prune(model, opt, cfg, st.cameras)
            if stats["pruned"]:
                self.errors.reset()
            yield Routine(it, "late_prune", stats)
        elif st.textures_started and schedule.every(cfg, cfg.realloc_every, it, shift):
            texels.realloc(model, opt, cfg.max_texture_res, cfg.texture_alloc, cfg.texture_sigma,
                           fresh_moments=cfg.texture_fresh_moments)
            if (budget := size_budget.fit(model, opt, cfg)) is not None:
                yield Routine(it, "budget", budget)

    def full_routine(self, st, it: int) -> dict:
        cfg = st.cfg
        gains = ({v.name: st.view_gains[i] for i, v in enumerate(st.train_views)}
                 if st.view_gains is not None and cfg.exposure_in_E else None)
        # init_shell: the far primitives the split/upscale ranking leaves out
        far = None if st.far_sphere is None else (lambda model: far_mask(model.means, *st.far_sphere))
        stats = full_routine(st.model, st.opt, cfg, it, st.train_views, st.render_fn, st.cameras, far,
                             gains=gains, step_errors=self.errors if cfg.error_from_steps else None)
        self.errors.reset()  # the primitives changed: the next routine's E starts from its own steps
        return stats

    def finish(self, st):
        if st.cfg.prune_opacity_final > 0:
            # As the authors' save: what can no longer reach alpha 1/255 goes before the model is evaluated and saved
            yield Routine(st.it, "final_prune", {"pruned": prune(st.model, st.opt, st.cfg.prune_opacity_final)})
        if st.cfg.texture_trim > 0:
            # Model only what the textures hold: texels below texture_trim in every channel go (texels.trim;
            # idempotent, so a resumed run that trims again changes nothing).
            yield Routine(st.it, "trim", texels.trim(st.model, st.opt, st.cfg.texture_trim))
