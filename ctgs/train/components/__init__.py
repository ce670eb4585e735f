"""Training components: the features a config turns on (parts.py), each called by the loop through the hooks of
ctgs.train.hooks with the run's narrow state, and what they are built from: the far shell (shell.py), virtual views
(virtual.py), the depth-normal term (normal.py), exposure gains (exposure.py), the time budget's cost model and
planner (budget.py)."""

from __future__ import annotations

from ctgs.train.components.parts import (ExposureCompensation, NormalTerm, Shell, SizeBudget, TimeBudget,
                                         VirtualCoverage, make_components)

__all__ = ["ExposureCompensation", "NormalTerm", "Shell", "SizeBudget", "TimeBudget", "VirtualCoverage",
           "make_components"]
