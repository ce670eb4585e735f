"""Checkpoints with everything needed to resume bit-for-bit on the CPU (written atomically by
ctgs.io.atomic.torch_save). On a GPU a resumed run is not bit-identical to an uninterrupted one: the CUDA
backward sums gradients with atomics, in an order that differs from run to run (docs/guide/gpu.md).

The checkpoint before the last is kept as prev.pt: a last.pt that cannot be read (a disk error, a file cut by a
copy, a filesystem that lost its last writes in a power cut) falls back to it, with a note saying so."""

from __future__ import annotations

import json
import os
import pickle
import random
import shutil
import sys
import zipfile

import numpy as np
import torch

from ctgs.errors import UserError, machine_fault
from ctgs.io import atomic
from ctgs.runs.folder import CHECKPOINTS

CKPT_NAME = "last.pt"
PREV_NAME = "prev.pt"
UNREADABLE_SUFFIX = ".unreadable"  # a last.pt that could not be read, once the run fell back to prev.pt


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
    return os.path.join(run_dir, CHECKPOINTS, CKPT_NAME)


def previous_path(run_dir: str) -> str:
    return os.path.join(run_dir, CHECKPOINTS, PREV_NAME)


def has_checkpoint(run_dir: str) -> bool:
    """Whether `run_dir` holds a checkpoint to resume from (the last, or the one before)."""
    return os.path.exists(checkpoint_path(run_dir)) or os.path.exists(previous_path(run_dir))


def readable_checkpoint(run_dir: str) -> tuple[str, int] | None:
    """(path, iteration) of the checkpoint `--resume` would start from (last.pt, else prev.pt), when it reads as a
    whole ctgs checkpoint; None when neither does (none yet, an empty checkpoints/, a cut file). The file is memory-
    mapped, not read: quick whatever its size. Changes nothing (load_checkpoint sets an unreadable last.pt aside)."""
    for path in (checkpoint_path(run_dir), previous_path(run_dir)):
        if not os.path.isfile(path):
            continue
        try:
            state = torch.load(path, map_location="cpu", weights_only=False, mmap=True)
            if isinstance(state, dict) and "model" in state and "iteration" in state:
                return path, int(state["iteration"])
        except _UNREADABLE:
            continue
    return None


def save_checkpoint(run_dir: str, state: dict) -> str:
    """Write `state` as last.pt (atomically, fsynced); the last.pt it replaces becomes prev.pt. At every moment
    at least one whole checkpoint is on disk under one of the two names. Returns last.pt's path."""
    path, prev = checkpoint_path(run_dir), previous_path(run_dir)
    if os.path.exists(path):
        # a hard link, then a rename over prev.pt: last.pt stays in place until the new one replaces it
        link = prev + ".link"
        if os.path.lexists(link):
            os.remove(link)
        try:
            os.link(path, link)
            os.replace(link, prev)
        except OSError:  # a filesystem without hard links: a copy
            with atomic.atomic_path(prev) as tmp:
                shutil.copyfile(path, tmp)
    atomic.torch_save(state, path)
    return path


# What torch.load raises on a cut, empty or foreign file (zip reader, pickle, EOF, the zip central directory).
_UNREADABLE = (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError, KeyError,
               AttributeError, TypeError, ImportError, IndexError, OSError)


def _read(path: str) -> dict:
    state = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(state, dict) or "iteration" not in state or "model" not in state:
        raise ValueError("not a ctgs training checkpoint")
    return state


def _why(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:160]


def load_checkpoint(run_dir: str) -> dict | None:
    """The last checkpoint of `run_dir`; prev.pt (with a note on stderr) when last.pt is missing or unreadable;
    None when there is neither. UserError naming both files when no checkpoint can be read."""
    path, prev = checkpoint_path(run_dir), previous_path(run_dir)
    if not os.path.exists(path) and not os.path.exists(prev):
        return None
    problems = []
    for candidate in (path, prev):
        if not os.path.exists(candidate):
            continue
        try:
            state = _read(candidate)
        except _UNREADABLE as exc:
            if isinstance(exc, OSError) and machine_fault(exc):  # not a damaged file: say what the machine did
                raise atomic.named(exc, candidate) from None
            problems.append(f"{candidate} unreadable ({_why(exc)})")
            continue
        if candidate == prev:
            said = problems[0] if problems else f"{path} missing"
            if problems:  # set aside (kept to look at): the next save must not rotate it into prev.pt
                os.replace(path, path + UNREADABLE_SUFFIX)
                said += f", moved to {os.path.basename(path) + UNREADABLE_SUFFIX}"
            print(f"ctgs train: {said}; resuming from the checkpoint before it, {prev} (iteration "
                  f"{int(state['iteration'])})", file=sys.stderr)
        return state
    raise UserError(f"{'; '.join(problems)}: no readable checkpoint to resume from; restart the run without "
                    "--resume into a new folder (-o)")


def _json_record(line: str) -> bool:
    try:
        return isinstance(json.loads(line), dict)
    except ValueError:
        return False


def cut_log(log_path: str, lines: int) -> int:
    """On resume: keep the first `lines` lines of the run's log (those written up to its checkpoint: the rest will be
    produced again); a damaged log (not UTF-8, cut lines) loses its unreadable lines, not the run. Returns the count
    kept."""
    raw = open(log_path, "rb").read().decode("utf-8", "replace") if os.path.exists(log_path) else ""
    kept = [line for line in raw.splitlines()[:lines] if _json_record(line)]
    atomic.write_text(log_path, "".join(line + "\n" for line in kept))  # a failed write names the log
    return len(kept)


def rerun_hint(run_dir: str) -> str:
    """What a diverged run keeps and how to go on: from its last checkpoint, or from the start."""
    last = load_checkpoint(run_dir)
    if last is None:
        return "no checkpoint was written yet; lower the learning rates (--set lr_...) and retrain"
    return (f"last good checkpoint {checkpoint_path(run_dir)} (iteration {last['iteration']}) kept; "
            f"lower the learning rates (--set lr_...) and rerun with --resume")


def main(argv: list[str] | None = None) -> int:
    """`python -m ctgs.runs.checkpoint RUN_DIR`: prints `--resume` when RUN_DIR holds a checkpoint a training can
    resume from, nothing otherwise (the Makefile's train rules ask it, not whether checkpoints/ exists)."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m ctgs.runs.checkpoint RUN_DIR", file=sys.stderr)
        return 2
    if readable_checkpoint(args[0]) is not None:
        print("--resume")
    return 0


if __name__ == "__main__":
    sys.exit(main())
