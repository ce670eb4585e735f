"""The run folder contract (read by export/eval):

RUN_DIR/config.toml         resolved config (scene_dir, images, holdout, backend, seed included)
RUN_DIR/model.pt            {"model": SurfelModel.state_dict(), "scene_dir", "images", "holdout", "iteration",
                            "config"} written atomically when training finishes
RUN_DIR/train_summary.json  {"iterations", "train_seconds", "backend", "device", "machine", "num_primitives",
                            "num_texels", "num_params", "final_test_psnr", "final_test_ssim", "method"}
RUN_DIR/checkpoints/        resume state;  RUN_DIR/log.jsonl  per-step / per-routine records
"""

from __future__ import annotations

import json
import os

import tomli_w
import torch

from ctgs.errors import UserError
from ctgs.model.surfels import SurfelModel
from ctgs.train.checkpoint import atomic_torch_save


def _atomic_write_text(path: str, text: str) -> None:
    tmp = f"{path}.tmp.{os.getpid()}"
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def write_config(run_dir: str, cfg_dict: dict) -> None:
    os.makedirs(run_dir, exist_ok=True)
    _atomic_write_text(os.path.join(run_dir, "config.toml"), tomli_w.dumps(cfg_dict))


def write_outputs(trainer, test_psnr: float, test_ssim: float) -> dict:
    cfg, model = trainer.cfg, trainer.model
    atomic_torch_save({"model": model.state_dict(), "scene_dir": cfg.scene_dir, "images": cfg.images,
                       "holdout": cfg.holdout, "iteration": trainer.it, "config": trainer.user_cfg.to_dict(),
                       "resolved_config": cfg.to_dict()},
                      os.path.join(trainer.run_dir, "model.pt"))
    backend = cfg.backend
    if backend == "auto":
        backend = "cuda" if trainer.device.type == "cuda" else "cpu"
    from ctgs.train.trainer import machine_name

    summary = {"iterations": trainer.it, "train_seconds": round(trainer.train_seconds, 2), "backend": backend,
               "device": str(trainer.device), "machine": machine_name(), "method": cfg.method,
               "num_primitives": model.num_primitives, "num_texels": model.num_texels,
               "num_params": model.num_params(), "final_test_psnr": test_psnr, "final_test_ssim": test_ssim,
               "preset": trainer.user_cfg.preset, "wall_seconds": round(trainer.wall_seconds(), 2),
               "image_pixels": trainer.pixels, "observed_values": trainer.observed_values(),
               "params_per_observed_value": model.num_params() / max(trainer.observed_values(), 1)}
    if trainer.planner is not None:
        summary.update(trainer.planner.summary())
    _atomic_write_text(os.path.join(trainer.run_dir, "train_summary.json"), json.dumps(summary, indent=2) + "\n")
    return summary


def load_run(run_dir: str, device: str | torch.device = "cpu") -> tuple[SurfelModel, dict]:
    """(model, info) of a finished run; info = model.pt's dict without "model" (+ "summary" if present)."""
    path = os.path.join(run_dir, "model.pt")
    if not os.path.exists(path):
        raise UserError(f"{run_dir}: no model.pt (training unfinished?); run or resume `ctgs train`")
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
        model = SurfelModel.from_state_dict(data["model"], device)
    except (KeyError, ValueError, RuntimeError, EOFError) as exc:
        raise UserError(f"{path}: unreadable model ({exc}); retrain the run") from None
    info = {k: v for k, v in data.items() if k != "model"}
    sp = os.path.join(run_dir, "train_summary.json")
    if os.path.exists(sp):
        with open(sp) as fh:
            info["summary"] = json.load(fh)
    return model, info
