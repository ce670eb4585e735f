"""Reading a finished run folder (written by `ctgs train RUN_DIR`): load_run, and with_scene for the scene folder its
views are read from on this machine.

RUN_DIR/model.pt = torch.save({"model": SurfelModel.state_dict(), "scene_dir", "images", "holdout", "iteration",
"config", "world_origin", "model_id"}); RUN_DIR/train_summary.json (optional here: only the training time comes from
it, and the model_id that pairs it with model.pt).
"""

from __future__ import annotations

import json
import os
import pickle
import zipfile
from dataclasses import dataclass, replace

import torch

from ctgs.errors import UserError, machine_fault
from ctgs.io import atomic
from ctgs.model.surfels import SurfelModel
from ctgs.runs.folder import MODEL_FILE, SUMMARY_FILE


@dataclass
class RunModel:
    run_dir: str
    model: SurfelModel
    scene_dir: str
    images: str  # image sub-folder of the scene the run trained on
    holdout: int  # every holdout-th image is a test view
    iteration: int
    config: dict
    summary: dict | None  # train_summary.json, None if absent
    model_bytes: int  # size of model.pt on disk
    # [3] float64: the model's frame origin in the scene's COLMAP frame (ctgs.scene.loader.world_origin); zero for
    # runs from before recentring existed (their scenes were never recentred)
    world_origin: tuple = (0.0, 0.0, 0.0)
    # the test views the scene's test_views.txt named when the run trained (None: every holdout-th view)
    test_views: list | None = None


def load_run(run_dir: str, device: torch.device | str = "cpu") -> RunModel:
    path = os.path.join(run_dir, MODEL_FILE)
    if not os.path.isdir(run_dir):
        raise UserError(f"{run_dir}: run folder not found; train one with `ctgs train SCENE -o {run_dir}`")
    if not os.path.isfile(path):
        raise UserError(f"{path}: no finished model in this run folder (training did not complete); "
                        f"run `ctgs train` to the end first")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        model = SurfelModel.from_state_dict(ckpt["model"], device=device)
    except OSError as exc:
        if machine_fault(exc):
            raise atomic.named(exc, path) from None  # the CLI's line for the machine says which and the fix
        raise _corrupt(path, exc) from None  # torch's reader on a cut file: EINVAL and the like
    except (KeyError, ValueError, RuntimeError, EOFError, TypeError, pickle.UnpicklingError,
            zipfile.BadZipFile, AttributeError, IndexError) as exc:
        # torch.load of random bytes raises UnpicklingError; of a cut file, RuntimeError from its zip reader
        raise _corrupt(path, exc) from None
    if not isinstance(ckpt, dict) or "scene_dir" not in ckpt:
        raise UserError(f"{path}: not a ctgs run model (no scene_dir); re-run `ctgs train`")
    summary = None
    spath = os.path.join(run_dir, SUMMARY_FILE)
    if os.path.isfile(spath):
        try:
            with open(spath) as f:
                summary = json.load(f)
        except ValueError as exc:
            raise UserError(f"{spath}: corrupt training summary ({exc}); re-run `ctgs train` or delete the file "
                            "(only the training time comes from it)") from None
    if summary is not None:
        _check_same_run(path, ckpt, spath, summary)
    return RunModel(run_dir=os.path.abspath(run_dir), model=model, scene_dir=ckpt["scene_dir"],
                    images=ckpt.get("images", "images"), holdout=int(ckpt.get("holdout", 8)),
                    iteration=int(ckpt.get("iteration", -1)), config=ckpt.get("config") or {},
                    summary=summary, model_bytes=os.path.getsize(path),
                    world_origin=tuple(float(x) for x in ckpt.get("world_origin") or (0.0, 0.0, 0.0)),
                    test_views=list(ckpt["test_views"]) if ckpt.get("test_views") else None)


def _check_same_run(path: str, ckpt: dict, spath: str, summary: dict) -> None:
    """UserError when model.pt and train_summary.json are of two runs (a model.pt copied in from another run folder):
    the summary's iterations and times would be reported for another model. Both name the model they were written
    with (model_id); runs from before that must agree on the iteration count."""
    ids = ckpt.get("model_id"), summary.get("model_id") if isinstance(summary, dict) else None
    ours = summary.get("iterations") if isinstance(summary, dict) else None
    if ids == (None, None) and (ours is None or int(ckpt.get("iteration", -1)) == int(ours)):
        return
    if ids[0] is not None and ids[0] == ids[1]:
        return
    raise UserError(f"{path}: another run's model (iteration {ckpt.get('iteration', '?')}), not the one {spath} "
                    f"describes (iteration {ours}); copy a run folder whole, or remove {SUMMARY_FILE} to use this "
                    "model.pt alone")


def _corrupt(path: str, exc: BaseException) -> UserError:
    detail = " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
    return UserError(f"{path}: unreadable or incomplete model ({detail}); it is corrupt: re-run `ctgs train` "
                     "(or `ctgs train --resume` while its checkpoints are there)")


def with_scene(run: RunModel, scene_dir: str | None = None) -> RunModel:
    """RUN with the scene folder its views are read from: SCENE_DIR when given (a run moved from the machine or folder
    it trained on: this machine's copy of the scene), else the one its model.pt names, which must exist here."""
    if scene_dir:
        if not os.path.isdir(scene_dir):
            raise UserError(f"{scene_dir}: scene folder not found; pass --scene the folder `ctgs sfm` made for this "
                            "run's photos")
        return replace(run, scene_dir=os.path.abspath(scene_dir))
    if not os.path.isdir(run.scene_dir):
        raise UserError(f"{os.path.join(run.run_dir, MODEL_FILE)}: trained on the scene folder {run.scene_dir}, which "
                        "is not on this machine; pass --scene DIR, this machine's copy of that scene")
    return run
