"""Checkpoints with everything needed to resume bit-for-bit on the CPU (written atomically by
ctgs.io.atomic.torch_save). On a GPU a resumed run is not bit-identical to an uninterrupted one: the CUDA
backward sums gradients with atomics, in an order that differs from run to run (docs/guide/gpu.md).

The checkpoint before the last is kept as prev.pt: a last.pt that cannot be read (a disk error, a file cut by a
copy, a filesystem that lost its last writes in a power cut) falls back to it, with a note saying so.

A checkpoint holds tensors and plain values only (numbers, strings, lists, tuples, dicts), so it is read with
torch.load(weights_only=True): unpickling a run folder someone else made runs no code of theirs. A checkpoint of
an earlier ctgs also holds numpy's random state as an array; it is read with numpy arrays allowed and nothing
else, with a note, and the next checkpoint is written without it. A file that names anything else is refused
(UntrustedCheckpoint), and nothing in it is run."""

from __future__ import annotations

import json
import os
import pickle
import random
import re
import shutil
import sys
import warnings
import zipfile

import numpy as np
import torch

from ctgs.errors import UserError, machine_fault
from ctgs.io import atomic
from ctgs.runs.folder import CHECKPOINTS

CKPT_NAME = "last.pt"
PREV_NAME = "prev.pt"
UNREADABLE_SUFFIX = ".unreadable"  # a last.pt that could not be read, once the run fell back to prev.pt


class UntrustedCheckpoint(UserError):
    """A checkpoint whose pickle names Python objects beyond tensors and plain values: refused, nothing run."""


def rng_state(gen: torch.Generator) -> dict:
    """Every random state a resumed run continues from, as tensors and plain values (numpy's key array as an int64
    tensor: a numpy array would need more than weights_only to read)."""
    kind, keys, pos, has_gauss, cached_gaussian = np.random.get_state()
    return {"torch": torch.get_rng_state(), "gen": gen.get_state(),
            "numpy": {"kind": str(kind), "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                      "has_gauss": int(has_gauss), "cached_gaussian": float(cached_gaussian)},
            "python": random.getstate(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def restore_rng(state: dict, gen: torch.Generator) -> None:
    torch.set_rng_state(state["torch"])
    gen.set_state(state["gen"])
    s = state["numpy"]
    if isinstance(s, dict):
        np.random.set_state((s["kind"], s["keys"].numpy().astype(np.uint32), s["pos"], s["has_gauss"],
                             s["cached_gaussian"]))
    else:  # an earlier checkpoint's: numpy's own tuple, its keys an array
        np.random.set_state(s)
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
    whole ctgs checkpoint; None when neither does (none yet, an empty checkpoints/, a cut file); UntrustedCheckpoint
    for a file that names Python objects (as --resume would). The file is memory-mapped, not read: quick whatever its
    size. Changes nothing (load_checkpoint sets an unreadable last.pt aside)."""
    for path in (checkpoint_path(run_dir), previous_path(run_dir)):
        if not os.path.isfile(path):
            continue
        try:
            state, _ = _load(path, mmap=True)
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


# What an earlier ctgs's checkpoint pickled beyond tensors and plain values: numpy's random state, one uint32 array.
# These rebuild an array of numbers and nothing else (an object array's items would need globals of their own,
# which stay refused). _reconstruct under both numpy 1's and numpy 2's module name.
_ARRAY_RECONSTRUCT = np.ndarray.__reduce__(np.zeros(1))[0]
_NUMPY_ARRAY_GLOBALS = [np.ndarray, np.dtype, type(np.dtype(np.uint32)),
                        (_ARRAY_RECONSTRUCT, "numpy.core.multiarray._reconstruct"),
                        (_ARRAY_RECONSTRUCT, "numpy._core.multiarray._reconstruct")]
_NUMPY_ARRAY_NAMES = {"numpy.ndarray", "numpy.dtype", f"numpy.dtypes.{type(np.dtype(np.uint32)).__name__}",
                      "numpy.core.multiarray._reconstruct", "numpy._core.multiarray._reconstruct"}


def _globals_named(path: str, exc: pickle.UnpicklingError) -> list[str]:
    """The globals (module.name) `path`'s pickle names beyond what weights_only allows, read without unpickling;
    [] when the file is damaged or no pickle of torch.save rather than a refusal."""
    try:
        return torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except (RuntimeError, ValueError, OSError, pickle.UnpicklingError, zipfile.BadZipFile):
        return re.findall(r"Unsupported global: GLOBAL (\S+)", str(exc))  # a pickle not in torch.save's zip


def _load(path: str, mmap: bool = False) -> tuple[object, bool]:
    """(what `path` holds, whether it is an earlier ctgs's checkpoint with numpy's random state as an array), read
    with weights_only=True; UntrustedCheckpoint when the file names any other Python object. torch's warnings on
    odd pickles are kept off the terminal: a refusal is said in its one line. `mmap` applies to torch.save's zip files
    (ctgs's own); another file is read as --resume would read it."""
    mmap = mmap and zipfile.is_zipfile(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap), False
        except pickle.UnpicklingError as exc:
            named = _globals_named(path, exc)
            if not named:
                raise  # damaged bytes: the callers' unreadable file
            beyond = [name for name in named if name not in _NUMPY_ARRAY_NAMES]
            if beyond:
                raise UntrustedCheckpoint(
                    f"{path}: holds Python objects, not only tensors and plain values ({', '.join(beyond[:3])}); "
                    "ctgs does not unpickle them, as that could run code from the file (nothing of it was run): "
                    "train into a new folder (-o) without --resume, or delete this checkpoint if the run is not "
                    "yours") from None
        with torch.serialization.safe_globals(_NUMPY_ARRAY_GLOBALS):
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap), True


def read_checkpoint(path: str) -> dict:
    """One checkpoint file, read as --resume reads it (a note for an earlier ctgs's; UntrustedCheckpoint, or what
    torch.load raises on a damaged file, otherwise)."""
    state, earlier = _load(path)
    if not isinstance(state, dict) or "iteration" not in state or "model" not in state:
        raise ValueError("not a ctgs training checkpoint")
    if earlier:
        print(f"ctgs train: {path} was written by an earlier ctgs (numpy's random state as an array): read with "
              "numpy arrays allowed and nothing else; the next checkpoint is written without it", file=sys.stderr)
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
            state = read_checkpoint(candidate)
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
    try:
        found = readable_checkpoint(args[0])
    except UntrustedCheckpoint as exc:  # nothing to resume that ctgs will read: the caller stops on this line
        print(f"ctgs: {exc}", file=sys.stderr)
        return 1
    if found is not None:
        print("--resume")
    return 0


if __name__ == "__main__":
    sys.exit(main())
