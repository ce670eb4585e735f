"""Writing a run folder: its config, its finished model and summary, and what they share.

The folder's files (see the package's docstring): CONFIG_FILE, LOG_FILE, CHECKPOINTS (ctgs.runs.checkpoint),
SUMMARY_FILE and MODEL_FILE. model.pt and train_summary.json name the model they were written with (model_id):
ctgs.runs.read refuses a model.pt copied in from another run.
"""

from __future__ import annotations

import json
import os
import platform
import uuid

import tomli_w

from ctgs.io import atomic

CONFIG_FILE = "config.toml"
LOG_FILE = "log.jsonl"
CHECKPOINTS = "checkpoints"
MODEL_FILE = "model.pt"
SUMMARY_FILE = "train_summary.json"


def machine_name() -> str:
    return f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)"


def write_config(run_dir: str, cfg_dict: dict) -> None:
    os.makedirs(run_dir, exist_ok=True)
    atomic.write_text(os.path.join(run_dir, CONFIG_FILE), tomli_w.dumps(cfg_dict))


def new_model_id() -> str:
    """The id that pairs a finished run's model.pt with its train_summary.json."""
    return uuid.uuid4().hex


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


def write_finished(run_dir: str, summary: dict, model: dict) -> None:
    """A finished run: `summary` as train_summary.json, then `model` (the weights and what they were trained on, the
    same model_id as the summary) as model.pt, both atomically. model.pt last: it marks a finished run, so a failed
    write (a full disk) leaves a run that --resume finishes, without a summary of a model that is not there."""
    summary_path = os.path.join(run_dir, SUMMARY_FILE)
    atomic.write_json(summary_path, summary)
    try:
        atomic.torch_save(model, os.path.join(run_dir, MODEL_FILE))
    except BaseException:
        os.remove(summary_path)
        raise
