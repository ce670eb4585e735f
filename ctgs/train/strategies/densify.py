"""The baselines' strategy: 3DGS/2DGS adaptive density control (ctgs.train.routines.densify), clone / split by the
view-space positional gradient accumulated over the steps, prune, opacity reset."""

from __future__ import annotations

from ctgs.train.config import schedule
from ctgs.train.events import Routine
from ctgs.train.routines.densify import GradAccumulator, densify_and_prune, reset_opacity
from ctgs.train.strategies.base import Strategy, settings_class

# Steps a reset's primitives get before a densification may prune them by opacity: 2DGS resets to 0.01 and prunes below
# 0.05 at its next densification, 100 steps later. A schedule scaled to a short run can densify sooner, which pruned
# every primitive of a 120-step demo run; such a densification then skips the opacity test (size pruning still runs).
RESET_RECOVERY_STEPS = 100


class Densify(Strategy):
    """`2dgs`: untextured surfels."""

    KEYS = ("densify_from", "densify_until", "densify_every", "densify_min_steps", "densify_grad_threshold",
            "percent_dense", "opacity_reset_every", "prune_opacity_2dgs", "max_primitives")
    Settings = settings_class("DensifySettings", KEYS, "The config keys of the 2DGS baseline's densification (`2dgs`).")
    texture_mode = "none"
    prune_rules = "opacity below its threshold, or larger than 0.1 x the scene extent"

    def __init__(self):
        self.acc = None  # the gradient statistics since the last densification
        self.last_reset = None  # iteration of the last opacity reset

    def initialize(self, st) -> None:
        self.acc = GradAccumulator(st.model.num_primitives, st.device)

    def restore(self, st, saved: dict) -> None:
        self.initialize(st)
        self.acc.load_state_dict({k: v.to(st.device) for k, v in saved["acc"].items()})
        self.last_reset = saved.get("last_reset")  # absent from older checkpoints

    def checkpoint(self, st) -> dict:
        return {"acc": {k: v.cpu() for k, v in self.acc.state_dict().items()}, "last_reset": self.last_reset}

    def post_backward(self, st, it: int, view) -> None:
        # the loss's gradient only: terms back-propagated after this hook are not in the statistics
        if it <= schedule.at(st.cfg, st.cfg.densify_until):
            self.acc.add_view(st.model.means, st.model.means.grad, view.camera)

    def step_end(self, st, it: int):
        cfg, shift = st.cfg, st.shift
        if schedule.densify_active(cfg, it, shift):
            prune_big = it > schedule.at(cfg, schedule.opacity_reset_period(cfg))
            recovered = self.last_reset is None or it - self.last_reset >= RESET_RECOVERY_STEPS
            yield Routine(it, "densify", densify_and_prune(st.model, st.opt, self.acc, cfg, st.extent, st.gen,
                                                           prune_big, prune_faint=recovered))
        if schedule.opacity_reset(cfg, it, shift):
            reset_opacity(st.model, st.opt)
            self.last_reset = it
            yield Routine(it, "opacity_reset", {})


class FixedTexture(Densify):
    """`fixed_texture`: the same densification, a fixed_texture_res^2 texture per primitive that stretches with it."""

    KEYS = (*Densify.KEYS, "fixed_texture_res")
    Settings = settings_class("FixedTextureSettings", KEYS,
                              "The config keys of the fixed-texture baseline (`fixed_texture`).")

    texture_mode = "fixed"
