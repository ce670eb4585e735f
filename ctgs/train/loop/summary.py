"""A finished training's outputs: its summary (train_summary.json) and its model (model.pt), written into the run
folder by ctgs.runs.write_finished (the folder's contract: ctgs.runs)."""

from __future__ import annotations

import os

from ctgs.model.extent import active_texels
from ctgs.runs import LOG_FILE, eval_peak, machine_name, new_model_id, write_finished


def write_outputs(trainer, test_psnr: float, test_ssim: float) -> dict:
    cfg, model = trainer.cfg, trainer.model
    backend = cfg.backend
    if backend == "auto":
        backend = "cuda" if trainer.device.type == "cuda" else "cpu"
    summary = {"iterations": trainer.it, "train_seconds": round(trainer.train_seconds, 2), "backend": backend,
               "device": str(trainer.device), "machine": machine_name(), "method": cfg.method,
               "num_primitives": model.num_primitives, "num_texels": model.num_texels,
               "num_texels_active": active_texels(model), "num_params": model.num_params(),
               "final_test_psnr": test_psnr, "final_test_ssim": test_ssim,
               "preset": trainer.user_cfg.preset, "wall_seconds": round(trainer.wall_seconds(), 2),
               "image_pixels": trainer.pixels, "observed_values": trainer.observed_values(),
               "params_per_observed_value": model.num_params() / max(trainer.observed_values(), 1),
               "scene_extent": trainer.extent, "near_plane": trainer.near,
               "seconds_in": {k: round(v, 2) for k, v in trainer.spent.items()}}
    # pairs model.pt with this summary: a model.pt copied in from another run is refused (ctgs.runs.load_run)
    summary["model_id"] = model_id = new_model_id()
    if cfg.max_params > 0:
        summary["max_params"] = cfg.max_params
        if trainer.user_cfg.max_params == 0 and trainer.user_cfg.max_params_per_value > 0:
            summary["max_params_per_value"] = trainer.user_cfg.max_params_per_value  # where the budget came from
    peak = eval_peak(os.path.join(trainer.run_dir, LOG_FILE))
    if peak is not None:
        views = ("validation" if cfg.validation_holdout > 0 else "test") if trainer.test_views else "training"
        summary["eval_peak"] = {**peak, "views": views}
    if trainer.time.clock is not None:  # the time budget's plan, or a fixed run's estimates
        summary.update(trainer.time.clock.summary())
    write_finished(trainer.run_dir, summary,
                   {"model": model.state_dict(), "scene_dir": cfg.scene_dir, "images": cfg.images,
                    "holdout": cfg.holdout, "iteration": trainer.it, "config": trainer.user_cfg.to_dict(),
                    "resolved_config": cfg.to_dict(), "world_origin": trainer.world_origin, "model_id": model_id,
                    **({"test_views": trainer.test_names} if trainer.test_names else {})})
    return summary
