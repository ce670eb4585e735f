"""The one interface through which the training loop (ctgs.train.loop.trainer.Trainer) calls what a run is made of,
and the narrow state it hands them.

A run is a *strategy* (how its primitives and textures change: ctgs.train.strategies, chosen by config `method`) and a
list of *components* (a feature the config turns on: the far shell, virtual views, the depth-normal term, the size
budget, exposure compensation, the time budget: ctgs.train.components). Both are `Component`s: the loop calls every
hook on the strategy first, then on each component in its order; each keeps its own state, and what it needs to
resume goes into the checkpoint under its own keys. `st` is the run's `TrainState` (below): the model, its optimiser,
the config, the views, the counters and the calendar; never the trainer, nor another part.

One iteration (Trainer._train_step):
    render(st, inputs, view, bg) -> (rgb, rasterized) | None   the step's training render, by the first part that
                                         makes it (init_shell: two renders composited); None: a plain render
    train_render(st, rgb, view) -> rgb   that render, before the loss (exposure gains)
    post_backward(st, it, view)          after the loss's backward, before the optimiser: gradient statistics, and
                                         terms rendered and back-propagated on their own (their gradients add up)
    post_step(st, it)                    after the optimiser step
    step_end(st, it) -> [Routine]        after the NaN guard: the schedule's routines (densification, splits, ...)
    timed_step(st, it, step_s, routine_s, events)   the step's and its routines' wall seconds
    log_fields(st, it) -> dict           extra fields of the step's log record
The run (Trainer.run): begin(st) -> [event] once it starts; timed(st, "eval" | "checkpoint", seconds, it) after a
periodic evaluation or checkpoint; after_step(st, it) -> [event] at the end of each iteration; finish(st) -> [Routine]
after the last iteration, before the final evaluation.
State: initialize(st) once the model of a fresh run exists; restore(st, saved) instead on --resume (saved: the whole
checkpoint; a key an older checkpoint lacks takes its default); checkpoint(st) -> dict: the keys it adds to one.
Calibration (ctgs.train.loop.calibration): step_seconds(st, view) -> its own seconds per training step (extra renders).

What each part reads of the state (and writes, marked =):
    ContentAware     cfg, device, model, opt (its routines edit both), it, train_views, cameras, render_fn,
                     textures_started (=), shift, textures_may_start, routine_kept, far_sphere, view_gains
    Densify          cfg, device, model, opt, extent, gen, shift
    Shell            model, render_fn, background
    VirtualCoverage  cfg, model, render_fn, device
    NormalTerm       cfg, model, device, check_finite
    SizeBudget       cfg, model, opt, it
    ExposureComp.    cfg, it, log, view_gains (=)
    TimeBudget       cfg, user_cfg, it, train_views, test_views, start_time, wall_before, spent, wall_seconds,
                     textures_started, calibration, log
Every other field is the loop's to write: the model and optimiser it builds, the counters, and the time budget's
decisions, which it takes from the TimeBudget part and hands on as values (the plan's length into cfg.iterations from
its Planned events, the calendar's shift, whether textures may start and whether a routine date is kept) together
with the calibration it times before the first plan.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import torch

from ctgs.render import render


@dataclass
class TrainView:
    name: str
    camera: object  # Camera on the training device
    image_t: torch.Tensor  # [H, W, 3] float32 in [0, 1]
    mask_t: torch.Tensor | None = None  # [H, W, 1] bool: the pixels in the loss and the scores (None: all)
    alpha_t: torch.Tensor | None = None  # [H, W, 1] a transparent photo's alpha (image_t is over cfg.background)


@dataclass(eq=False)
class TrainState:
    """What the loop hands a strategy's and a component's hooks: the run's model and optimiser (replaced by the loop
    on a start, a resume and for the calibration's copy: read them from here each time), its config, views and
    counters, and the services the loop lends them. The loop owns it; parts change only the fields the module
    docstring marks."""

    cfg: object  # the config resolved for the scene (ctgs.train.config.rules); cfg.iterations: the planned length
    user_cfg: object  # the config as given (saved with the run)
    device: torch.device
    train_views: list[TrainView]
    test_views: list[TrainView]
    extent: float  # the scene's extent (the learning rates' and the baselines' size scale)
    background: torch.Tensor  # [3] what renders are composited over (cfg.background)
    gen: torch.Generator  # the run's generator (view order, random backgrounds, the baselines' splits)
    log: Callable[[dict], None]  # append a record to the run's log.jsonl
    check_finite: Callable[..., None]  # check_finite(loss): raise TrainingDiverged on NaN/Inf (the loop's guard)
    model: object = None  # the SurfelModel
    opt: object = None  # its SurfelAdam
    it: int = 0  # iterations done
    start_time: float = 0.0  # time.monotonic() when this session's command started
    wall_before: float = 0.0  # wall seconds of earlier sessions of the run (resume)
    spent: dict = field(default_factory=dict)  # wall seconds of routines, evaluations and checkpoints so far
    textures_started: bool = False  # a content-aware run's textures are allocated
    # The time budget's decisions (ctgs.train.components.TimeBudget), as the loop hands them on: the periodic calendar's
    # phase shift (ctgs.train.config.schedule.every); whether textures may start (not before the plan rests on
    # measured steps); whether this iteration's full-routine date is kept (a budget holds routines to their share).
    shift: float = 0.0
    textures_may_start: bool = True
    routine_kept: bool = True
    # The seconds the loop timed on a copy of the model before the first plan (ctgs.train.loop.calibration.calibrate:
    # step, render, textured step, E of one view), None where no plan or estimate needs them
    calibration: tuple | None = None
    # init_shell: (centre, reach) of the sphere beyond which primitives are the far shell's (ctgs.train.routines.far);
    # None: no shell
    far_sphere: tuple | None = None
    # exposure_comp: [training views, 3] their gains after this step's update, in train_views' order (None: no gains)
    view_gains: torch.Tensor | None = None

    @property
    def cameras(self) -> list:
        return [v.camera for v in self.train_views]

    def render_fn(self, inputs, camera, error_image=None, background=None, backward_stats=None):
        """A render of `inputs` through `camera` at the run's backend, SH degree and background."""
        return render(inputs, camera, backend=self.cfg.backend, sh_degree=self.model.sh_degree,
                      background=self.background if background is None else background, error_image=error_image,
                      backward_stats=backward_stats)

    def wall_seconds(self) -> float:
        """Wall-clock seconds of this run so far, earlier sessions included."""
        return self.wall_before + time.monotonic() - self.start_time


class Component:
    """No-op hooks (module docstring); a part overrides those it needs."""

    def initialize(self, st: TrainState) -> None:
        pass

    def restore(self, st: TrainState, saved: dict) -> None:
        pass

    def checkpoint(self, st: TrainState) -> dict:
        return {}

    def begin(self, st: TrainState):
        return ()

    def render(self, st: TrainState, inputs, view, bg):
        return None

    def train_render(self, st: TrainState, rgb, view):
        return rgb

    def post_backward(self, st: TrainState, it: int, view) -> None:
        pass

    def post_step(self, st: TrainState, it: int) -> None:
        pass

    def step_end(self, st: TrainState, it: int):
        return ()

    def timed_step(self, st: TrainState, it: int, step_s: float, routine_s: float, events) -> None:
        pass

    def timed(self, st: TrainState, what: str, seconds: float, it: int) -> None:
        pass

    def log_fields(self, st: TrainState, it: int) -> dict:
        return {}

    def after_step(self, st: TrainState, it: int):
        return ()

    def finish(self, st: TrainState):
        return ()

    def step_seconds(self, st: TrainState, view) -> float:
        return 0.0
