"""The run folder contract (read by export/eval):

RUN_DIR/config.toml         resolved config (scene_dir, images, holdout, backend, seed included)
RUN_DIR/model.pt            {"model": SurfelModel.state_dict(), "scene_dir", "images", "holdout", "iteration",
                            "config", "world_origin"} written atomically when training finishes; world_origin [3]:
                            the working frame's origin in the COLMAP model's frame (zero unless recentred)
RUN_DIR/train_summary.json  {"iterations", "train_seconds", "backend", "device", "machine", "num_primitives",
                            "num_texels", "num_params", "final_test_psnr", "final_test_ssim", "method", ...};
                            a --time-budget run adds its plan (time_budget_s, planned_iterations_initial, ...), a
                            fresh run of fixed length its wall-time estimates (estimated_wall_s, estimated_at_it);
                            eval_peak: the periodic evaluation with the highest PSNR ({"it", "psnr", "ssim", "views"});
                            seconds_in: wall seconds spent in routines, periodic evaluations and checkpoints
RUN_DIR/checkpoints/        resume state;  RUN_DIR/log.jsonl  per-step / per-routine records

Reading a finished run is ctgs.train.run_model.load_run (weights only: model.pt holds no pickled objects).
"""

from __future__ import annotations

import json
import os
import platform
import uuid

import tomli_w

from ctgs.io import atomic


def machine_name() -> str:
    return f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)"


def write_config(run_dir: str, cfg_dict: dict) -> None:
    os.makedirs(run_dir, exist_ok=True)
    atomic.write_text(os.path.join(run_dir, "config.toml"), tomli_w.dumps(cfg_dict))


def eval_peak(log_path: str) -> dict | None:
    """{"it", "psnr", "ssim"} of the periodic evaluation with the highest PSNR in a run's log (the earliest on a
    tie), None without evaluations. Read, for the record: a length chosen from test views would be tuned on them."""
    best = None
    try:
        with open(log_path) as fh:
            for line in fh:
                if '"test"' not in line:
                    continue
                d = json.loads(line)
                if d.get("type") == "test" and d.get("psnr") is not None and (best is None or d["psnr"] > best["psnr"]):
                    best = {"it": int(d["it"]), "psnr": float(d["psnr"]), "ssim": float(d.get("ssim") or 0.0)}
    except (OSError, ValueError):
        return None
    return best


def write_outputs(trainer, test_psnr: float, test_ssim: float) -> dict:
    cfg, model = trainer.cfg, trainer.model
    backend = cfg.backend
    if backend == "auto":
        backend = "cuda" if trainer.device.type == "cuda" else "cpu"
    summary = {"iterations": trainer.it, "train_seconds": round(trainer.train_seconds, 2), "backend": backend,
               "device": str(trainer.device), "machine": machine_name(), "method": cfg.method,
               "num_primitives": model.num_primitives, "num_texels": model.num_texels,
               "num_params": model.num_params(), "final_test_psnr": test_psnr, "final_test_ssim": test_ssim,
               "preset": trainer.user_cfg.preset, "wall_seconds": round(trainer.wall_seconds(), 2),
               "image_pixels": trainer.pixels, "observed_values": trainer.observed_values(),
               "params_per_observed_value": model.num_params() / max(trainer.observed_values(), 1),
               "scene_extent": trainer.extent, "near_plane": trainer.near,
               "seconds_in": {k: round(v, 2) for k, v in trainer.spent.items()}}
    # pairs model.pt with this summary: a model.pt copied in from another run is refused (ctgs.train.run_model)
    summary["model_id"] = model_id = uuid.uuid4().hex
    if cfg.max_params > 0:
        summary["max_params"] = cfg.max_params
        if trainer.user_cfg.max_params == 0 and trainer.user_cfg.max_params_per_value > 0:
            summary["max_params_per_value"] = trainer.user_cfg.max_params_per_value  # where the budget came from
    peak = eval_peak(os.path.join(trainer.run_dir, "log.jsonl"))
    if peak is not None:
        views = ("validation" if cfg.validation_holdout > 0 else "test") if trainer.test_views else "training"
        summary["eval_peak"] = {**peak, "views": views}
    if trainer.time.clock is not None:  # the time budget's plan, or a fixed run's estimates
        summary.update(trainer.time.clock.summary())
    summary_path = os.path.join(trainer.run_dir, "train_summary.json")
    atomic.write_json(summary_path, summary)
    # model.pt last: it marks a finished run, so a failed write (a full disk) leaves a run that --resume finishes
    try:
        atomic.torch_save({"model": model.state_dict(), "scene_dir": cfg.scene_dir, "images": cfg.images,
                           "holdout": cfg.holdout, "iteration": trainer.it, "config": trainer.user_cfg.to_dict(),
                           "resolved_config": cfg.to_dict(), "world_origin": trainer.world_origin,
                           "model_id": model_id},
                          os.path.join(trainer.run_dir, "model.pt"))
    except BaseException:
        os.remove(summary_path)
        raise
    return summary

