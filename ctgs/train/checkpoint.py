"""Checkpoints with everything needed to resume bit-for-bit on the CPU (written atomically by
ctgs.io.atomic.torch_save). On a GPU a resumed run is not bit-identical to an uninterrupted one: the CUDA
backward sums gradients with atomics, in an order that differs from run to run (docs/guide/gpu.md)."""

from __future__ import annotations

import os
import random

import numpy as np
import torch

CKPT_NAME = "last.pt"


def rng_state(gen: torch.Generator) -> dict:
    return {"torch": torch.get_rng_state(), "gen": gen.get_state(), "numpy": np.random.get_state(),
            "python": random.getstate(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def restore_rng(state: dict, gen: torch.Generator) -> None:
    torch.set_rng_state(state["torch"])
    gen.set_state(state["gen"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        # One state per GPU of the machine that saved it; a resume may see fewer (or other) GPUs.
        for i, s in enumerate(state["cuda"][: torch.cuda.device_count()]):
            torch.cuda.set_rng_state(s, i)


def checkpoint_path(run_dir: str) -> str:
    return os.path.join(run_dir, "checkpoints", CKPT_NAME)


def load_checkpoint(run_dir: str) -> dict | None:
    path = checkpoint_path(run_dir)
    if not os.path.exists(path):
        return None
    return torch.load(path, map_location="cpu", weights_only=False)
