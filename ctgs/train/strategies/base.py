"""What every training strategy has besides the hooks (ctgs.train.hooks): a strategy sees the run's TrainState and
keeps its own state."""

from __future__ import annotations

from ctgs.train.hooks import Component


class Strategy(Component):
    texture_mode = "content_aware"  # the model's texture mode (ctgs.train.start.init.init_model)
    starts_textures = False  # textures allocated partway (at texture_start), not with the model
    # what its pruning removes (said when a routine leaves no primitive)
    prune_rules = "opacity below its threshold"

    def step_stats(self, st):
        """A ctgs.render.BackwardStats for this step's render to fill in its backward, or None (no statistics)."""
        return None
