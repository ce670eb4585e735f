"""What the strategies do to the model on the schedule's dates: the content-aware full and late routines (passes.py)
from the error E (error.py), splits and pruning (split.py), texel-size changes and texture reallocation (texels.py),
k_min (kmin.py), the size budget's coarsening (size_budget.py); the baselines' densification (densify.py); the
optimiser-aware edits of the primitive set they share (edit.py)."""
