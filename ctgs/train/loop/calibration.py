"""The time budget's calibration (ctgs.train.components.TimeBudget): training steps timed as the loop takes them, on
a copy of the trainer's model and optimiser (the run's own are not touched)."""

from __future__ import annotations

import copy
import time

import numpy as np
import torch

from ctgs.train.config import schedule
from ctgs.train.step.adam import ALL_PARAMS
from ctgs.train.routines.error import compute_E
from ctgs.train.step.loss import training_loss


def median_seconds(fn, reps: int = 3, device: torch.device | None = None) -> float:
    """Median wall seconds of fn(); on a CUDA device the queued kernels are waited for (a launch is not a step)."""
    cuda = device is not None and device.type == "cuda"
    times = []
    for _ in range(reps):
        if cuda:
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def calibrate(tr) -> tuple[float, float, float | None, float | None]:
    """Median seconds, timed on a copy of tr's model and optimiser, of a training step as the loop takes it
    (forward+backward, Adam, the components' own terms), of a forward on a training view, and for a strategy whose
    textures start partway and have not yet, of a training step once they have and of E's render of one view (None
    otherwise): the planner's texture-start jump and routine cost."""
    model, opt = tr.model, tr.opt
    try:
        tr.model, tr.opt = copy.deepcopy(model), copy.deepcopy(opt)
        step_s = _time_steps(tr, 1)
        with torch.no_grad():
            render_s = median_seconds(lambda: tr.render_fn(tr.model.render_inputs(), tr.train_views[0].camera),
                                      device=tr.device)
        textured_s = error_view_s = None
        if tr.strategy.starts_textures and not tr.strategy.textures_started:
            tr.strategy.start_textures(tr)
            textured_s = _time_steps(tr, schedule.texture_start(tr.cfg) + 1)
            error_view_s = median_seconds(lambda: compute_E(tr.model, tr.train_views[:1], tr.render_fn,
                                                            tr.cfg.lambda_ssim), device=tr.device)
    finally:
        tr.model, tr.opt = model, opt
    return step_s, render_s, textured_s, error_view_s


def _time_steps(tr, it: int) -> float:
    """Median seconds of a training step of tr.model on the first training view at iteration `it`'s learning rates,
    plus the components' shares (ctgs.train.hooks: step_seconds)."""
    view = tr.train_views[0]
    lrs = schedule.learning_rates(tr.cfg, it, tr.extent, tr.model.sh.shape[1], tr.device)

    def step():
        for name in ALL_PARAMS:
            getattr(tr.model, name).grad = None
        inputs = tr.model.render_inputs()
        rgb, rasterized = tr._training_render(inputs, view, None)
        training_loss(rgb, view.image_t, tr.model, view.camera, tr.cfg, rasterized=rasterized,
                      textures=inputs.textures).total.backward()
        tr.opt.step(tr.model, lrs)
        # as the loop does after every step: learning rates that make the copy diverge make the run diverge
        # (said as such, before a render of non-finite parameters fails on its input checks)
        tr._check_finite(None)

    return median_seconds(step, device=tr.device) + sum(part.step_seconds(tr, view) for part in tr.parts)
