"""Run folders: what `ctgs train SCENE -o RUN_DIR` writes, and every later stage (export, eval, render, mesh, the
Slurm launcher) and the benchmarks read.

RUN_DIR/config.toml         resolved config (scene_dir, images, holdout, backend, seed included)
RUN_DIR/model.pt            {"model": SurfelModel.state_dict(), "scene_dir", "images", "holdout", "iteration",
                            "config", "world_origin", "model_id"} written atomically when training finishes;
                            world_origin [3]: the working frame's origin in the COLMAP model's frame (zero unless
                            recentred)
RUN_DIR/train_summary.json  {"iterations", "train_seconds", "backend", "device", "machine", "num_primitives",
                            "num_texels", "num_params", "final_test_psnr", "final_test_ssim", "method", "model_id",
                            ...}; a --time-budget run adds its plan (time_budget_s, planned_iterations_initial, ...),
                            a fresh run of fixed length its wall-time estimates (estimated_wall_s, estimated_at_it);
                            eval_peak: the periodic evaluation with the highest PSNR ({"it", "psnr", "ssim",
                            "views"}); seconds_in: wall seconds spent in routines, periodic evaluations and checkpoints
RUN_DIR/checkpoints/        resume state (ctgs.runs.checkpoint: last.pt and the one before, prev.pt)
RUN_DIR/log.jsonl           per-step / per-routine records

One concern a module:

- `folder`: the file names, writing the config and the finished model and summary (write_finished), eval_peak
- `read`: load_run (weights only: model.pt holds no pickled objects), RunModel, with_scene
- `checkpoint`: writing and reading checkpoints; `python -m ctgs.runs.checkpoint RUN_DIR` prints `--resume` when
  RUN_DIR holds one a training can resume from
- `scene`: the scene a training loads from its config (training_scene), and the one a finished run was trained on
  (run_scene)

The names below are resolved on first use, so that `python -m ctgs.runs.checkpoint` and a Slurm job's checks load
only what they use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ctgs.runs.folder import (CHECKPOINTS, CONFIG_FILE, LOG_FILE, MODEL_FILE, SUMMARY_FILE, eval_peak,
                                  machine_name, new_model_id, write_config, write_finished)
    from ctgs.runs.read import RunModel, load_run, with_scene
    from ctgs.runs.scene import run_scene, training_scene

_MODULES = {
    "ctgs.runs.folder": ("CHECKPOINTS", "CONFIG_FILE", "LOG_FILE", "MODEL_FILE", "SUMMARY_FILE", "eval_peak",
                         "machine_name", "new_model_id", "write_config", "write_finished"),
    "ctgs.runs.read": ("RunModel", "load_run", "with_scene"),
    "ctgs.runs.scene": ("run_scene", "training_scene"),
}
_EXPORTS = {name: module for module, names in _MODULES.items() for name in names}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
