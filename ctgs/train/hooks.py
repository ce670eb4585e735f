"""The one interface through which the training loop (ctgs.train.loop.trainer.Trainer) calls what a run is made of.

A run is a *strategy* (how its primitives and textures change: ctgs.train.strategies, chosen by config `method`) and a
list of *components* (a feature the config turns on: the far shell, virtual views, the depth-normal term, the size
budget, exposure compensation, the time budget: ctgs.train.components). Both are `Component`s: the trainer calls every hook on the
strategy first, then on each component in the order of `Trainer.parts`; each keeps its own state, and what it needs
to resume goes into the checkpoint under its own keys. `tr` is the Trainer (model, optimiser, config, views, log).

One iteration (Trainer._train_step):
    render(tr, inputs, view, bg) -> (rgb, rasterized) | None   the step's training render, by the first part that
                                         makes it (init_shell: two renders composited); None: a plain render
    train_render(tr, rgb, view) -> rgb   that render, before the loss (exposure gains)
    post_backward(tr, it, view)          after the loss's backward, before the optimiser: gradient statistics, and
                                         terms rendered and back-propagated on their own (their gradients add up)
    post_step(tr, it)                    after the optimiser step
    step_end(tr, it) -> [Routine]        after the NaN guard: the schedule's routines (densification, splits, ...)
    timed_step(tr, it, step_s, routine_s, events)   the step's and its routines' wall seconds
    log_fields(tr, it) -> dict           extra fields of the step's log record
The run (Trainer.run): begin(tr) -> [event] once it starts; timed(tr, "eval" | "checkpoint", seconds, it) after a
periodic evaluation or checkpoint; after_step(tr, it) -> [event] at the end of each iteration; finish(tr) -> [Routine]
after the last iteration, before the final evaluation.
State: initialize(tr) once the model of a fresh run exists; restore(tr, state) instead on --resume (state: the whole
checkpoint; a key an older checkpoint lacks takes its default); checkpoint() -> dict: the keys it adds to one.
Calibration (ctgs.train.loop.calibration): step_seconds(tr, view) -> its own seconds per training step (extra renders).
"""

from __future__ import annotations


class Component:
    """No-op hooks (module docstring); a part overrides those it needs."""

    def initialize(self, tr) -> None:
        pass

    def restore(self, tr, state: dict) -> None:
        pass

    def checkpoint(self) -> dict:
        return {}

    def begin(self, tr):
        return ()

    def render(self, tr, inputs, view, bg):
        return None

    def train_render(self, tr, rgb, view):
        return rgb

    def post_backward(self, tr, it: int, view) -> None:
        pass

    def post_step(self, tr, it: int) -> None:
        pass

    def step_end(self, tr, it: int):
        return ()

    def timed_step(self, tr, it: int, step_s: float, routine_s: float, events) -> None:
        pass

    def timed(self, tr, what: str, seconds: float, it: int) -> None:
        pass

    def log_fields(self, tr, it: int) -> dict:
        return {}

    def after_step(self, tr, it: int):
        return ()

    def finish(self, tr):
        return ()

    def step_seconds(self, tr, view) -> float:
        return 0.0
