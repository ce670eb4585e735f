"""A run folder followed while it trains (`ctgs view RUN_DIR`): its newest model as a web bundle, and its progress
(iteration, loss, test PSNR, time left) from its log, for the page to poll (ctgs.viewer.server: /live/...).

Reads RUN_DIR only, and only these names in it: model.pt (a finished run's model), checkpoints/last.pt, else
checkpoints/prev.pt (a training's), log.jsonl, config.toml and the lock file; each after checking it is a plain file
whose real path lies inside RUN_DIR (a link leading out of it is not followed), and nothing is ever written there. The
scene's cameras are read once, at the start, from the scene folder config.toml names (as `ctgs view MODEL_DIR` reads
a model's), so that the page can jump to them. Bundles are built in a private temporary folder, one per model shown;
the page fetches every file of one by its version number, so a newer model landing meanwhile never mixes into it.

A run folder being written never breaks the page: checkpoints are written under a hidden temporary name and renamed
(ctgs.io.atomic), so last.pt and prev.pt are whole files, never read while half-written; a file that still cannot be
read (a copy cut short) is passed over, the model shown stays, and the status says which file and why. The log grows
a line at a time: only whole lines are read, a line that is no JSON record is skipped, and a log rewritten by a
resume (shorter, another file) is read again from its start. Files are read with torch.load(weights_only=True):
tensors and plain values only, no code of the file's runs (an earlier ctgs's checkpoint also holds numpy's random
state as an array of numbers, which is allowed and nothing else).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import threading
import time
import tomllib

import numpy as np
import torch

from ctgs.formats.web_bundle import scene_cameras, write_web_bundle
from ctgs.io import owner
from ctgs.io.atomic import pid_alive
from ctgs.io.lock import LOCK_NAME
from ctgs.model.surfels import SurfelModel
from ctgs.runs.checkpoint import CKPT_NAME, PREV_NAME
from ctgs.runs.folder import CHECKPOINTS, CONFIG_FILE, LOG_FILE, MODEL_FILE

# Points of the loss curve the page gets (every record up to this many, then every other one, and so on).
MAX_CURVE = 400
RUN_KIND = "run"  # the marker `ctgs train` puts in its run folder (ctgs.io.owner; ctgs.stages.train RUN_KIND)
# Bundles kept besides the newest: a page may still be fetching the one before.
KEEP_BUNDLES = 2
# Recent step records the time left of a run without a time budget is extrapolated from.
RATE_WINDOW = 20
# What a checkpoint pickles beyond tensors and plain values (an earlier ctgs's numpy random state): arrays of numbers.
_ARRAY_RECONSTRUCT = np.ndarray.__reduce__(np.zeros(1))[0]
_ARRAY_GLOBALS = [np.ndarray, np.dtype, type(np.dtype(np.uint32)),
                  (_ARRAY_RECONSTRUCT, "numpy.core.multiarray._reconstruct"),
                  (_ARRAY_RECONSTRUCT, "numpy._core.multiarray._reconstruct")]


def is_run_folder(folder: str) -> bool:
    """Whether `folder` is a run folder of `ctgs train`: marked as one (from its first moment), or its config with a
    log, checkpoints or a model (a run from before folders were marked)."""
    names = set(os.listdir(folder)) if os.path.isdir(folder) else set()
    return owner.kind_of(folder) == RUN_KIND or (CONFIG_FILE in names and bool(names & {LOG_FILE, CHECKPOINTS,
                                                                                           MODEL_FILE}))


class LiveRun:
    """Follows RUN_DIR; `status()` reads what changed and returns the page's status, `bundle_dir(version)` the folder
    of a model shown. work_dir: a private folder for the bundles (removed by the caller). cameras: the scene's
    cameras for the bundles (None: read from the scene config.toml names, [] when it is not on this machine)."""

    def __init__(self, run_dir: str, work_dir: str, cameras: list[dict] | None = None):
        self.run_dir = os.path.realpath(run_dir)
        self.work_dir = work_dir
        self.name = os.path.basename(self.run_dir)
        self.config = self._config()
        self.notes: list[str] = []
        self.find_cameras = cameras is None
        self.cameras = cameras or []
        self._config_read()
        self.lock = threading.Lock()
        self.log = _LogTail(self.path(LOG_FILE))
        self.version = 0
        self.shown: dict | None = None  # {"version", "iteration", "source", "num_surfels", "num_texels", "file"}
        self.shown_id = None  # identity of the file shown (device, inode, size, mtime)
        self.failed: dict = {}  # identity -> why, of files that could not be read
        self.problem: str | None = None

    # ---- the run folder, read-only -------------------------------------------------------------------------
    def path(self, *parts: str) -> str | None:
        """RUN_DIR/parts when it is a plain file inside RUN_DIR (a link may not lead out of it), else None."""
        p = os.path.join(self.run_dir, *parts)
        real = os.path.realpath(p)
        if not real.startswith(self.run_dir + os.sep) or not os.path.isfile(real):
            return None
        return real

    def _config(self) -> dict:
        p = self.path(CONFIG_FILE)
        try:
            with open(p, "rb") as f:
                return tomllib.load(f)
        except (TypeError, OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
            return {}

    def _config_read(self) -> None:
        """The config and, unless given, the scene's cameras, once config.toml is there (a run that just started may
        not have written it yet: asked again at every status)."""
        if not self.config:
            self.config = self._config()
        if self.config and self.find_cameras:
            self.find_cameras = False
            self.cameras = self._cameras()

    def _cameras(self) -> list[dict]:
        scene = self.config.get("scene_dir")
        if not scene or not os.path.isdir(scene):
            self.notes.append(f"the run's scene ({scene or 'unknown'}) is not on this machine: no cameras to jump to")
            return []
        try:
            return scene_cameras(scene, self.config.get("images", "images"), int(self.config.get("holdout", 8)))
        except Exception as exc:  # noqa: BLE001 - the page works without cameras; say why there are none
            self.notes.append(f"{scene}: cameras unreadable ({' '.join(str(exc).split())[:160]})")
            return []

    def state(self) -> str:
        """finished (model.pt), training (the lock's holder is a live process here), stopped, or diverged."""
        if self.path(MODEL_FILE):
            return "finished"
        if self.log.diverged:
            return "diverged"
        p = self.path(LOCK_NAME)
        try:
            with open(p, encoding="utf-8") as f:
                info = json.loads(f.read() or "{}")
            if info.get("host") == socket.gethostname() and pid_alive(int(info["pid"])):
                return "training"
            if info.get("host") and info.get("host") != socket.gethostname():
                return "training"  # (another machine's: it holds the lock while it trains)
        except (TypeError, OSError, ValueError, KeyError):
            pass
        return "stopped"

    # ---- the model -------------------------------------------------------------------------------------
    def _candidates(self) -> list[str]:
        finished = self.path(MODEL_FILE)
        if finished:
            return [finished]
        return [p for p in (self.path(CHECKPOINTS, CKPT_NAME), self.path(CHECKPOINTS, PREV_NAME)) if p]

    def refresh_model(self) -> None:
        """Show the newest readable model (model.pt, else last.pt, else prev.pt) when it is not the one shown."""
        for path in self._candidates():
            try:
                st = os.stat(path)
            except OSError:
                continue
            ident = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
            if ident == self.shown_id:
                return  # the newest whole file is the one shown
            if ident in self.failed:
                continue
            try:
                model, iteration = _read_model(path)
            except Exception as exc:  # noqa: BLE001 - any unreadable file: keep what is shown, say why
                why = " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
                self.failed[ident] = f"{os.path.relpath(path, self.run_dir)} unreadable ({why})"
                continue
            self._show(model, iteration, path, ident)
            return

    def _show(self, model: SurfelModel, iteration: int, path: str, ident) -> None:
        version = self.version + 1
        out = os.path.join(self.work_dir, f"v{version}")
        source = os.path.relpath(path, self.run_dir)
        write_web_bundle(model, out, self.cameras, extra={"live": {"iteration": iteration, "source": source}})
        self.version, self.shown_id = version, ident
        self.shown = {"version": version, "iteration": iteration, "source": source,
                      "num_surfels": model.num_primitives, "num_texels": int(model.num_texels)}
        shutil.rmtree(os.path.join(self.work_dir, f"v{version - KEEP_BUNDLES}"), ignore_errors=True)

    def bundle_dir(self, version: int) -> str | None:
        folder = os.path.join(self.work_dir, f"v{int(version)}")
        return folder if version > self.version - KEEP_BUNDLES and os.path.isdir(folder) else None

    # ---- the page's status -------------------------------------------------------------------------------
    def status(self) -> dict:
        """What changed in the run folder since the last call, then the page's status (JSON-able). Never raises for
        what is in the run folder: a problem is said in `problems`."""
        with self.lock:
            problems = []
            self._config_read()
            try:
                self.log.read()
            except Exception as exc:  # noqa: BLE001 - a log that cannot be read: said, the rest still shown
                problems.append(f"{LOG_FILE}: {' '.join(str(exc).split())[:160]}")
            try:
                self.refresh_model()
            except Exception as exc:  # noqa: BLE001 - a bundle that cannot be built: said, the last one stays
                problems.append(f"the newest model could not be shown ({' '.join(str(exc).split())[:160]})")
            # files newer than the model shown that could not be read (an older one is of no interest any more)
            problems += [why for ident, why in self.failed.items() if self.shown_id is None or
                         ident[3] > self.shown_id[3]]
            state = self.state()
            log = self.log
            planned = log.planned or int(self.config.get("iterations", 0)) or None
            return {
                "run": self.name, "state": state, "model": self.shown, "notes": self.notes + problems,
                "iteration": log.last_step.get("it"), "planned": planned,
                "loss": log.last_step.get("loss"), "train_psnr": log.last_step.get("psnr"),
                "primitives": log.last_step.get("n"), "texels": log.last_step.get("texels"),
                "seconds_left": 0.0 if state == "finished" else self._seconds_left(planned) if state == "training"
                else None,
                "test": log.tests, "loss_curve": log.curve,
            }

    def _seconds_left(self, planned: int | None) -> float | None:
        log = self.log
        last = log.last_step
        if not last:
            return None
        since = max(0.0, time.time() - log.mtime) if log.mtime else 0.0
        if log.budget_s:  # a --time-budget run ends with its budget (the wall clock counts from its command's start)
            return max(0.0, log.budget_s - float(last.get("wall", 0.0)) - since)
        if planned is None or len(log.recent) < 2:
            return None
        (i0, w0), (i1, w1) = log.recent[0], log.recent[-1]
        if i1 <= i0:
            return None
        return max(0.0, (planned - i1) * (w1 - w0) / (i1 - i0) - since)


def _read_model(path: str) -> tuple[SurfelModel, int]:
    """(model, iteration) of a model.pt or a checkpoint, read as data only (weights_only; memory-mapped: a checkpoint's
    optimiser state is never read)."""
    with torch.serialization.safe_globals(_ARRAY_GLOBALS):
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    if not isinstance(state, dict) or not isinstance(state.get("model"), dict):
        raise ValueError("not a ctgs model or checkpoint")
    model = SurfelModel.from_state_dict(state["model"])
    return model, int(state.get("iteration", -1))


class _LogTail:
    """The records of a run's log.jsonl read so far, a whole line at a time from where the last read stopped."""

    def __init__(self, path: str | None):
        self.path = path
        self.reset()

    def reset(self) -> None:
        self.offset, self.ident, self.mtime = 0, None, 0.0
        self.last_step: dict = {}
        self.tests: list[list] = []  # [it, psnr, ssim]
        self.curve: list[list] = []  # [it, loss], thinned to at most MAX_CURVE points
        self.stride, self.seen_steps = 1, 0
        self.recent: list[tuple] = []  # (it, wall) of the last RATE_WINDOW step records
        self.planned: int | None = None
        self.budget_s: float | None = None
        self.diverged = False

    def read(self) -> None:
        if self.path is None:
            return
        try:
            fh = open(self.path, "rb")
        except FileNotFoundError:
            self.reset()
            return
        with fh:
            st = os.fstat(fh.fileno())
            if (st.st_dev, st.st_ino) != self.ident or st.st_size < self.offset:
                self.reset()  # rewritten (a resume cuts the log to its checkpoint): read from the start
                self.ident = (st.st_dev, st.st_ino)
            self.mtime = st.st_mtime
            fh.seek(self.offset)
            data = fh.read(max(0, st.st_size - self.offset))
        end = data.rfind(b"\n")
        if end < 0:
            return  # no whole line yet
        self.offset += end + 1
        for line in data[:end].split(b"\n"):
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if isinstance(rec, dict):
                self._take(rec)

    def _take(self, rec: dict) -> None:
        kind = rec.get("type")
        num = lambda v: v if isinstance(v, (int, float)) and math.isfinite(v) else None  # noqa: E731
        if kind == "step" and isinstance(rec.get("it"), int):
            self.last_step = {k: rec.get(k) for k in ("it", "loss", "psnr", "n", "texels", "wall")}
            self.recent = (self.recent + [(rec["it"], float(num(rec.get("wall")) or 0.0))])[-RATE_WINDOW:]
            self.seen_steps += 1
            if (self.seen_steps - 1) % self.stride == 0 and num(rec.get("loss")) is not None:
                self.curve.append([rec["it"], rec["loss"]])
                if len(self.curve) > MAX_CURVE:
                    self.curve, self.stride = self.curve[::2], self.stride * 2
        elif kind == "test" and num(rec.get("psnr")) is not None:
            self.tests.append([rec.get("it"), rec["psnr"], num(rec.get("ssim"))])
        elif kind == "plan":
            if num(rec.get("iterations")):
                self.planned = int(rec["iterations"])
            if num(rec.get("time_budget_s")):
                self.budget_s = float(rec["time_budget_s"])
        elif kind == "diverged":
            self.diverged = True
