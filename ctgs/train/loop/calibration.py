"""The time budget's calibration (ctgs.train.components.TimeBudget; the loop times it before the first plan and hands
the seconds on as TrainState.calibration): training steps timed as the loop takes them, on a copy of the run's model
and optimiser (the run's own are not touched)."""

from __future__ import annotations

import copy

import torch

from ctgs.train.components.budget import median_seconds
from ctgs.train.config import schedule
from ctgs.train.routines.error import compute_E
from ctgs.train.step.adam import ALL_PARAMS
from ctgs.train.step.loss import training_loss


def calibrate(trainer) -> tuple[float, float, float | None, float | None]:
    """Median seconds, timed on a copy of the trainer's model and optimiser, of a training step as the loop takes it
    (forward+backward, Adam, the components' own terms), of a forward on a training view, and for a strategy whose
    textures start partway and have not yet, of a training step once they have and of E's render of one view (None
    otherwise): the planner's texture-start jump and routine cost."""
    st, strategy = trainer.state, trainer.strategy
    model, opt = st.model, st.opt
    try:
        st.model, st.opt = copy.deepcopy(model), copy.deepcopy(opt)
        step_s = _time_steps(trainer, 1)
        with torch.no_grad():
            render_s = median_seconds(lambda: st.render_fn(st.model.render_inputs(), st.train_views[0].camera),
                                      device=st.device)
        textured_s = error_view_s = None
        if strategy.starts_textures and not st.textures_started:
            strategy.start_textures(st)
            textured_s = _time_steps(trainer, schedule.texture_start(st.cfg) + 1)
            error_view_s = median_seconds(lambda: compute_E(st.model, st.train_views[:1], st.render_fn,
                                                            st.cfg.lambda_ssim), device=st.device)
    finally:
        st.model, st.opt = model, opt
    return step_s, render_s, textured_s, error_view_s


def _time_steps(trainer, it: int) -> float:
    """Median seconds of a training step of the state's model on the first training view at iteration `it`'s learning
    rates, plus the parts' shares (ctgs.train.hooks: step_seconds)."""
    st = trainer.state
    view = st.train_views[0]
    lrs = schedule.learning_rates(st.cfg, it, st.extent, st.model.sh.shape[1], st.device)

    def step():
        for name in ALL_PARAMS:
            getattr(st.model, name).grad = None
        inputs = st.model.render_inputs()
        rgb, rasterized = trainer.training_render(inputs, view, None)
        training_loss(rgb, view.image_t, st.model, view.camera, st.cfg, rasterized=rasterized,
                      textures=inputs.textures).total.backward()
        st.opt.step(st.model, lrs)
        # as the loop does after every step: learning rates that make the copy diverge make the run diverge
        # (said as such, before a render of non-finite parameters fails on its input checks)
        st.check_finite(None)

    return median_seconds(step, device=st.device) + sum(part.step_seconds(st, view) for part in trainer.parts)
