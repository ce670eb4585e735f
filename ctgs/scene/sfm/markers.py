"""Resuming: the work folder `.NAME.sfm-work` beside SCENE_DIR holds one marker per finished step (its seconds and CPU
seconds) and a record of the inputs each step depends on; a step is redone when its inputs, or an earlier step's,
changed, and a damaged record redoes every step."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys

from ctgs.io import atomic
from ctgs.scene.sfm.options import SfmOptions

STEPS = ("features", "matches", "mapping", "undistort", "pyramid")


def work_dir(scene_dir: str) -> str:
    return os.path.join(os.path.dirname(scene_dir), f".{os.path.basename(scene_dir)}.sfm-work")


def step_done(work: str, step: str) -> bool:
    return os.path.isfile(os.path.join(work, f"{step}.done"))


def mark_done(work: str, step: str, seconds: float, cpu_seconds: float = 0.0) -> None:
    atomic.write_text(os.path.join(work, f"{step}.done"), f"{seconds:.3f} {cpu_seconds:.3f}\n")


def step_figures(marker: str) -> tuple[float, float]:
    """(seconds, CPU seconds) a step's marker recorded; NaN for what a damaged marker no longer says (the step's
    result is checked by the steps after it, not by its marker's figures)."""
    try:
        with open(marker, encoding="utf-8") as f:
            figures = [float(x) for x in f.read().split()[:2]]
    except (ValueError, UnicodeDecodeError):
        figures = []
    figures += [float("nan")] * (2 - len(figures))
    return figures[0], figures[1]


def invalidate_from(work: str, step: str) -> None:
    for later in STEPS[STEPS.index(step):]:
        marker = os.path.join(work, f"{later}.done")
        if os.path.exists(marker):
            os.remove(marker)


def inputs_digest(images_dir: str, names: list[str]) -> str:
    """Which photos these are: their names, byte sizes and first 64 KiB (not their dates: a copied folder is the
    same capture)."""
    h = hashlib.sha256()
    for name in names:
        path = os.path.join(images_dir, name)
        h.update(f"{name}\0{os.path.getsize(path)}\0".encode())
        with open(path, "rb") as f:
            h.update(f.read(1 << 16))
    return h.hexdigest()


def inputs_fingerprint(images_dir: str, names: list[str], opts: SfmOptions, matcher: str, mapper: str,
                       extractor: str = "opencv") -> dict:
    """What each step's result depends on; a step is redone when its part (or an earlier one) changed."""
    files = [[n, os.path.getsize(os.path.join(images_dir, n)), int(os.path.getmtime(os.path.join(images_dir, n)))]
             for n in names]
    return {"images_dir": images_dir, "files": files, "max_image_size": opts.max_image_size,
            "max_features": opts.max_features, "extractor": extractor, "matcher": matcher, "mapper": mapper}


# The fingerprint keys each step depends on first (later steps depend on everything before them).
_STEP_KEYS = (("features", ("images_dir", "files", "max_image_size", "max_features", "extractor")),
              ("matches", ("matcher",)), ("mapping", ("mapper",)))


def _read_fingerprint(path: str) -> dict | None:
    """The inputs a previous run recorded, or None when there is none or it cannot be read (a damaged file means the
    previous work cannot be trusted: every step is redone)."""
    try:
        with open(path, encoding="utf-8") as f:
            previous = json.load(f)
    except FileNotFoundError:
        return None
    except (ValueError, UnicodeDecodeError, RecursionError, IsADirectoryError):  # cut, garbled, nested, a folder
        print(f"ctgs: {path}: unreadable (damaged); the SfM steps are redone from the photos", file=sys.stderr)
        return None
    return previous if isinstance(previous, dict) else None


def prepare_work(work: str, fingerprint: dict, force: bool) -> None:
    """Reuse a previous run's work folder only for the steps whose inputs and options are unchanged."""
    path = os.path.join(work, "inputs.json")
    previous = _read_fingerprint(path) if os.path.isdir(work) and not force else None
    if previous is not None:
        if previous == fingerprint:
            return
        for step, keys in _STEP_KEYS:
            if any(previous.get(k) != fingerprint[k] for k in keys):
                invalidate_from(work, step)
                if step == "features" and os.path.exists(os.path.join(work, "database.db")):
                    os.remove(os.path.join(work, "database.db"))
                break
    else:
        shutil.rmtree(work, ignore_errors=True)
        os.makedirs(work)
    atomic.write_json(path, fingerprint, indent=None)
