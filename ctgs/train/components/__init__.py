"""Training components: the features a config turns on, each called by the loop through the hooks of
ctgs.train.hooks with the run's TrainState: the far shell (shell.py: `Shell` and its geometry), virtual views
(virtual.py: `VirtualCoverage`), and in parts.py the depth-normal term (from normal.py), the size budget, exposure
gains (from exposure.py) and the time budget (its cost model and planner: budget.py); `make_components` lists a
run's."""

from __future__ import annotations

from ctgs.train.components.parts import ExposureCompensation, NormalTerm, SizeBudget, TimeBudget, make_components
from ctgs.train.components.shell import Shell
from ctgs.train.components.virtual import VirtualCoverage

__all__ = ["ExposureCompensation", "NormalTerm", "Shell", "SizeBudget", "TimeBudget", "VirtualCoverage",
           "make_components"]
