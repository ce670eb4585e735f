"""The baselines' strategy: 3DGS/2DGS adaptive density control (ctgs.train.routines.densify), clone / split by the
view-space positional gradient accumulated over the steps, prune, opacity reset."""

from __future__ import annotations

from ctgs.train.config import schedule
from ctgs.train.events import Routine
from ctgs.train.routines.densify import GradAccumulator, densify_and_prune, reset_opacity
from ctgs.train.strategies.base import Strategy


class Densify(Strategy):
    """`2dgs`: untextured surfels."""

    texture_mode = "none"
    prune_rules = "opacity below its threshold, or larger than 0.1 x the scene extent"

    def __init__(self):
        self.acc = None  # the gradient statistics since the last densification

    def initialize(self, st) -> None:
        self.acc = GradAccumulator(st.model.num_primitives, st.device)

    def restore(self, st, saved: dict) -> None:
        self.initialize(st)
        self.acc.load_state_dict({k: v.to(st.device) for k, v in saved["acc"].items()})

    def checkpoint(self, st) -> dict:
        return {"acc": {k: v.cpu() for k, v in self.acc.state_dict().items()}}

    def post_backward(self, st, it: int, view) -> None:
        # the loss's gradient only: terms back-propagated after this hook are not in the statistics
        if it <= schedule.at(st.cfg, st.cfg.densify_until):
            self.acc.add_view(st.model.means, st.model.means.grad, view.camera)

    def step_end(self, st, it: int):
        cfg, shift = st.cfg, st.calendar.shift
        if schedule.densify_active(cfg, it, shift):
            prune_big = it > schedule.at(cfg, cfg.opacity_reset_every)
            yield Routine(it, "densify", densify_and_prune(st.model, st.opt, self.acc, cfg, st.extent, st.gen,
                                                           prune_big))
        if schedule.opacity_reset(cfg, it, shift):
            reset_opacity(st.model, st.opt)
            yield Routine(it, "opacity_reset", {})


class FixedTexture(Densify):
    """`fixed_texture`: the same densification, a fixed_texture_res^2 texture per primitive that stretches with it."""

    texture_mode = "fixed"
