"""The training loop: one iteration = one random training view, loss, backward, Adam, schedule.

`Trainer.run()` is a generator of typed events (ctgs/train/events.py); it writes the JSON-lines log,
atomic checkpoints, and on success model.pt + train_summary.json into the run folder.
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import os
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from ctgs.ops import fused
from ctgs.errors import Terminated, UserError
from ctgs.io import atomic
from ctgs.metrics.ssim import ssim
from ctgs.model.surfels import SurfelModel
from ctgs.train import checkpoint as ckpt
from ctgs.train import rules, schedule, size_budget, texels
from ctgs.train.adam import ALL_PARAMS, SurfelAdam
from ctgs.train.budget import BudgetPlanner
from ctgs.train.config import TrainConfig
from ctgs.train.densify import RESET_OPACITY, GradAccumulator, densify_and_prune, reset_opacity
from ctgs.train.error import compute_E
from ctgs.train.events import Checkpoint, Done, Estimated, Eval, Planned, Routine, Step
from ctgs.train.exposure import Exposure
from ctgs.train.fill import fill_points
from ctgs.train.init import init_model
from ctgs.train.kmin import compute_k_min, view_coverage
from ctgs.train.loss import training_loss
from ctgs.train.normal import normal_loss
from ctgs.train.routines import full_routine, late_routine
from ctgs.train.shell import composite, far_mask, open_mask, scene_sphere, shell_points
from ctgs.train.virtual import coverage_loss, virtual_views


def _median_seconds(fn, reps: int = 3, device: torch.device | None = None) -> float:
    """Median wall seconds of fn(); on a CUDA device the queued kernels are waited for (a launch is not a step)."""
    cuda = device is not None and device.type == "cuda"
    times = []
    for _ in range(reps):
        if cuda:
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _all_finite(t: torch.Tensor) -> bool:
    # min/max propagate NaN and expose +-inf in one pass without a bool temporary of the tensor's size.
    lo, hi = torch.aminmax(t.detach())
    return bool(torch.isfinite(lo) & torch.isfinite(hi))


class TrainingDiverged(UserError):
    """NaN/Inf in the loss or the parameters: training stopped, the last checkpoint is kept."""

    exit_code = 4


@dataclass
class TrainView:
    name: str
    camera: object  # Camera on the training device
    image_t: torch.Tensor  # [H, W, 3] float32 in [0, 1]


def pick_device(cfg: TrainConfig) -> torch.device:
    if cfg.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if cfg.device == "cuda" and not torch.cuda.is_available():
        raise UserError("config device=cuda but no CUDA device is available: use --set device=cpu")
    return torch.device(cfg.device)


def make_views(views, device) -> list[TrainView]:
    out = []
    for v in views:
        if v.image is None:
            raise UserError(f"{v.image_path}: image not loaded")
        out.append(TrainView(v.name, v.camera.to(device), torch.from_numpy(np.ascontiguousarray(v.image)).to(device)))
    return out


def _json_record(line: str) -> bool:
    try:
        return isinstance(json.loads(line), dict)
    except ValueError:
        return False


class Trainer:
    """cfg: the config as given (saved with the run); self.cfg is its copy resolved for this scene's image size
    (ctgs/train/rules.py) whose `iterations` is the planned run length (`--time-budget` re-plans it).
    start_time: time.monotonic() when the command started (the time budget counts from there)."""

    def __init__(self, cfg: TrainConfig, scene, run_dir: str, resume: bool = False, start_time: float | None = None):
        self.user_cfg = cfg
        self.run_dir = run_dir
        self.start_time = time.monotonic() if start_time is None else start_time
        self.device = pick_device(cfg)
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)  # OpenMP spin-waiting on an oversubscribed CPU costs ~5x
        if self.device.type == "cpu":
            fused.tune_allocator()  # freed [T, 3] temporaries are reused, not faulted in afresh
        self.extent = float(scene.extent)
        self.near = float(scene.train[0].camera.near) if scene.train else None  # the scene's (loader.near_plane)
        self.num_sfm_points = len(scene.points)
        self.world_origin = [float(x) for x in getattr(scene, "origin", (0.0, 0.0, 0.0))]  # saved with the model
        # init_shell: the sphere that tells the shell's far primitives from the scene's (ctgs.train.shell.far_mask).
        self.sphere = scene_sphere(scene.points, scene.train) if cfg.init_shell > 0 else None
        self.train_views = make_views(scene.train, self.device)
        self.test_views = make_views(scene.test, self.device)
        if not self.train_views:
            raise UserError(f"{scene.root}: no training images (check --images and holdout)")
        self.cameras = [v.camera for v in self.train_views]
        # init_shell: per training view, the pixels where the shell may show in training renders (shell.composite).
        self.open_px = None if self.sphere is None else {
            v.name: torch.from_numpy(open_mask(scene.points, v.camera)).to(self.device) for v in self.train_views}
        self.pixels = float(np.median([v.camera.width * v.camera.height for v in self.train_views]))
        # virtual_coverage: virtual views half a camera step from each training camera, with the pixels the
        # training cameras hold (ctgs.train.virtual), visited in a fixed shuffled cycle (resume-safe: by iteration).
        self.virtual = []
        if cfg.virtual_coverage > 0:
            self.virtual = [replace(vv, camera=vv.camera.to(self.device), mask=vv.mask.to(self.device))
                            for vv in virtual_views([v.name for v in self.train_views], self.cameras, scene.points,
                                                    pixels=cfg.virtual_pixels)]
            if not self.virtual:
                raise UserError(f"{scene.root}: virtual_coverage found no virtual view with {cfg.virtual_pixels} "
                                "pixels (it needs two training cameras with SfM points in view); set "
                                "virtual_coverage = 0")
        self.last_normal = float("nan")  # lambda_normal: the last step's depth-normal term (logged)
        self.virtual_order = torch.randperm(len(self.virtual), generator=torch.Generator().manual_seed(cfg.seed + 1))
        # max_params_per_value: the size budget from the observed values (an explicit max_params wins)
        budgeted = rules.with_size_budget(cfg, self.observed_values())
        # views' worth of scene in the capture (the primitive cap is per pixel of a typical view: ctgs.train.rules)
        self.coverage = (view_coverage(torch.from_numpy(np.asarray(scene.points, np.float32)), self.cameras)
                         if cfg.primitives_per_pixel > 0 else 1.0)
        self.cfg = rules.resolve(budgeted, self.pixels, self.coverage)
        self.planner = None  # --time-budget: plans the run's length
        self.estimator = None  # a fresh run of fixed length: the same cost model, estimating its wall time only
        self.wall_before = 0.0  # wall seconds of earlier sessions of this run (resume)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        os.makedirs(os.path.join(run_dir, "checkpoints"), exist_ok=True)
        self.log_path = os.path.join(run_dir, "log.jsonl")
        state = ckpt.load_checkpoint(run_dir) if resume else None
        if resume and state is None:
            raise UserError(f"{run_dir}: --resume but no checkpoint in checkpoints/; start without --resume")
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % 2**32)
        # exposure_comp: a per-channel gain per training image on its training renders (ctgs.train.exposure)
        self.view_index = {v.name: i for i, v in enumerate(self.train_views)}
        self.exposure = (Exposure(len(self.train_views), self.device, cfg.lr_exposure, cfg.exposure_channels)
                         if cfg.exposure_comp else None)
        if state is None:
            mode = {"content_aware": "content_aware", "2dgs": "none", "fixed_texture": "fixed"}[cfg.method]
            # extra initial points, appended after the SfM points' cap: the far shell's, then the fill's
            extra = shell_points(scene.points, scene.train, cfg.init_shell) if cfg.init_shell > 0 else (None, None)
            if cfg.init_fill:
                fill = fill_points(scene.points, scene.train)
                extra = tuple(f if e is None else np.concatenate([e, f]) for e, f in zip(extra, fill))
            cap = rules.init_point_cap(budgeted, self.pixels, self.coverage)
            self.model = init_model(scene.points, scene.point_colors, max_points=cap,
                                    opacity=cfg.init_opacity, max_sh_degree=cfg.max_sh_degree,
                                    random_rotation=cfg.random_rotation, normals=cfg.init_normals, texture_mode=mode,
                                    fixed_res=cfg.fixed_texture_res, seed=cfg.seed, extra_points=extra[0],
                                    extra_colors=extra[1])
            self._to_device()
            self.model.k_min = compute_k_min(self.model.means.detach(), self.cameras)
            self.opt = SurfelAdam(self.model, cfg.adam_eps)
            self.it = 0
            self.train_seconds = 0.0
            self.perm, self.perm_pos = None, 0
            self.acc = GradAccumulator(self.model.num_primitives, self.device)
            self.log_lines = 0
            self.textures_started = False
            open(self.log_path, "w").close()
        else:
            self._restore(state)
        if cfg.time_budget > 0:
            self.planner = BudgetPlanner(self.cfg, cfg.time_budget * 60.0, self.start_time - self.wall_before,
                                         len(self.train_views), len(self.test_views))
            if state is not None and "planner" in state:
                self.planner.load_state_dict(state["planner"])
                if self.textures_started and self.planner.tex_at is None:  # a checkpoint of an earlier planner
                    self.planner.observe_texture_start(min(self.it, schedule.texture_start(self.cfg)))
        elif state is None:
            self.estimator = BudgetPlanner(self.cfg, None, self.start_time, len(self.train_views), len(self.test_views))

    # ---- state -----------------------------------------------------------------------------------
    def _to_device(self) -> None:
        for name in ALL_PARAMS:
            setattr(self.model, name, getattr(self.model, name).detach().to(self.device).requires_grad_(True))
        for name in ("k_min", "t2p_exp", "tex_res", "tex_offset"):
            setattr(self.model, name, getattr(self.model, name).to(self.device))

    def _restore(self, state: dict) -> None:
        self.model = SurfelModel.from_state_dict(state["model"], self.device)
        self._to_device()
        self.opt = SurfelAdam(self.model, self.cfg.adam_eps)
        self.opt.load_state_dict(state["opt"], self.device)
        self.it = int(state["iteration"])
        self.cfg.iterations = int(state.get("planned_iterations", self.cfg.iterations))
        self.wall_before = float(state.get("wall_seconds", 0.0))
        self.textures_started = bool(state.get("textures_started", self.it >= schedule.texture_start(self.cfg)))
        self.train_seconds = float(state["train_seconds"])
        self.perm = state["perm"]
        self.perm_pos = int(state["perm_pos"])
        self.acc = GradAccumulator(self.model.num_primitives, self.device)
        self.acc.load_state_dict({k: v.to(self.device) for k, v in state["acc"].items()})
        ckpt.restore_rng(state["rng"], self.gen)
        if self.exposure is not None and "exposure" in state:
            self.exposure.load_state_dict(state["exposure"])
        # Drop log lines written after the checkpoint (they will be produced again).
        # A damaged log (not UTF-8, cut lines) loses its unreadable lines, not the run.
        raw = open(self.log_path, "rb").read().decode("utf-8", "replace") if os.path.exists(self.log_path) else ""
        lines = [line for line in raw.splitlines()[: int(state["log_lines"])] if _json_record(line)]
        self.log_lines = len(lines)
        atomic.write_text(self.log_path, "".join(line + "\n" for line in lines))  # a failed write names the log

    def _state(self) -> dict:
        return {"model": self.model.state_dict(), "opt": self.opt.state_dict(), "iteration": self.it,
                "train_seconds": self.train_seconds, "perm": self.perm, "perm_pos": self.perm_pos,
                "acc": {k: v.cpu() for k, v in self.acc.state_dict().items()}, "rng": ckpt.rng_state(self.gen),
                "log_lines": self.log_lines, "config": self.user_cfg.to_dict(), "planned_iterations": self.cfg.iterations,
                "textures_started": self.textures_started, "wall_seconds": self.wall_seconds(),
                **({"planner": self.planner.state_dict()} if self.planner else {}),
                **({"exposure": self.exposure.state_dict()} if self.exposure is not None else {})}

    def observed_values(self) -> int:
        """Values the model is fitted to: RGB of every training pixel."""
        return int(sum(3 * v.camera.width * v.camera.height for v in self.train_views))

    def wall_seconds(self) -> float:
        """Wall-clock seconds of this run so far, earlier sessions included."""
        return self.wall_before + time.monotonic() - self.start_time

    def _save_checkpoint(self) -> str:
        self._check_finite(None, full=True)
        return ckpt.save_checkpoint(self.run_dir, self._state())  # the one before stays as prev.pt

    def _log(self, record: dict) -> None:
        atomic.append_text(self.log_path, json.dumps(record) + "\n")  # a full disk: OSError naming the log
        self.log_lines += 1

    # ---- rendering -------------------------------------------------------------------------------
    def render_fn(self, inputs, camera, error_image=None, background=None):
        from ctgs.render import render

        return render(inputs, camera, backend=self.cfg.backend, sh_degree=self.model.sh_degree,
                      background=self.background if background is None else background, error_image=error_image)

    def _next_view(self) -> TrainView:
        if self.perm is None or self.perm_pos >= len(self.perm):
            self.perm = torch.randperm(len(self.train_views), generator=self.gen).tolist()
            self.perm_pos = 0
        v = self.train_views[self.perm[self.perm_pos]]
        self.perm_pos += 1
        return v

    @torch.no_grad()
    def evaluate(self) -> tuple[float, float]:
        """Mean PSNR / SSIM over the test views (train views if there are none)."""
        views = self.test_views or self.train_views
        inputs = self.model.render_inputs()
        psnrs, ssims = [], []
        for v in views:
            rgb = self.render_fn(inputs, v.camera).rgb.clamp(0, 1)
            mse = ((rgb - v.image_t) ** 2).mean().clamp_min(1e-12)
            psnrs.append(float(-10 * torch.log10(mse)))
            ssims.append(float(ssim(rgb, v.image_t)))
        return float(np.mean(psnrs)), float(np.mean(ssims))

    # ---- guard -----------------------------------------------------------------------------------
    def _check_finite(self, loss: torch.Tensor | None, full: bool = False) -> None:
        """NaN/Inf in the loss, or in a parameter the last optimiser step made non-finite (its fused
        kernel counts them as it writes; parameters it updated otherwise are scanned here). full: scan
        every parameter (before a checkpoint is written, so no NaN can reach one)."""
        bad = None
        if loss is not None and not bool(torch.isfinite(loss)):
            bad = "loss"
        else:
            names = ALL_PARAMS if full else self.opt.nonfinite + self.opt.unchecked
            for name in ALL_PARAMS:
                p = getattr(self.model, name)
                if name in names and p.numel() and (name in self.opt.nonfinite or not _all_finite(p)):
                    bad = f"parameter {name}"
                    break
        if bad is None:
            return
        path = ckpt.checkpoint_path(self.run_dir)
        last = ckpt.load_checkpoint(self.run_dir)
        where = (f"last good checkpoint {path} (iteration {last['iteration']}) kept; "
                 f"lower the learning rates (--set lr_...) and rerun with --resume") if last else \
            "no checkpoint was written yet; lower the learning rates (--set lr_...) and retrain"
        self._log({"type": "diverged", "it": self.it, "what": bad})
        raise TrainingDiverged(f"{self.run_dir}: NaN/Inf in {bad} at iteration {self.it}; {where}")

    def _no_primitives_left(self, events) -> None:
        """The routines removed every primitive: say so (a NaN loss on an empty model would blame the lrs)."""
        kind = events[-1].kind if events else "a"
        rules = "opacity below its threshold" + (", or larger than 0.1 x the scene extent"
                                                 if self.cfg.method != "content_aware" else "")
        self._log({"type": "diverged", "it": self.it, "what": "no primitives left"})
        raise TrainingDiverged(
            f"{self.run_dir}: the {kind} routine at iteration {self.it} pruned every primitive ({rules}), nothing is "
            f"left to train; the run started from {self.num_sfm_points} SfM points: too few points, points outside "
            f"the cameras' views or images that do not belong to the model end this way: check the scene (`ctgs sfm` "
            f"writes a report) and --images")

    # ---- loop ------------------------------------------------------------------------------------
    def _training_render(self, inputs, view, bg):
        """(rgb, rasterized) of a training step: one render over `bg` (None: cfg.background), or with init_shell
        the scene composited over the far primitives where the view sees past the SfM points (two renders)."""
        if self.open_px is None:
            out = self.render_fn(inputs, view.camera, background=bg)
            return out.rgb, out.rasterized
        return composite(self.render_fn, inputs, view.camera, far_mask(self.model.means, *self.sphere),
                         self.open_px[view.name], self.background if bg is None else bg)

    def _virtual_step(self, it: int) -> None:
        """virtual_coverage: every virtual_every-th step, one virtual view's coverage term, rendered and
        back-propagated on its own (its gradients add to the step's; the 2dgs gradient statistics exclude it)."""
        if not self.virtual or it % self.cfg.virtual_every:
            return
        vv = self.virtual[int(self.virtual_order[(it // self.cfg.virtual_every) % len(self.virtual)])]
        alpha = self.render_fn(self.model.render_inputs(), vv.camera).alpha
        (self.cfg.virtual_coverage * coverage_loss(alpha, vv)).backward()

    def _normal_active(self, it: int) -> bool:
        return self.cfg.lambda_normal > 0 and it >= schedule.at_int(self.cfg, self.cfg.normal_from)

    def _normal_step(self, it: int, view: TrainView) -> None:
        """lambda_normal: from normal_from on, 2DGS's depth-normal consistency term on the step's view, rendered and
        back-propagated on its own (its gradients add to the step's; the 2dgs gradient statistics exclude it)."""
        if not self._normal_active(it):
            return
        term = normal_loss(self.model.render_inputs(), view.camera, self.cfg.backend)
        self.last_normal = float(term.detach())
        if not math.isfinite(self.last_normal):  # (the parameters are scanned once per step, after the optimiser)
            self._check_finite(term)
        (self.cfg.lambda_normal * term).backward()

    def _calibrate(self) -> tuple[float, float, float | None, float | None]:
        """Median seconds, timed on a copy of the model and optimiser (the run's own are not touched), of a
        training step as the loop takes it (forward+backward, Adam), of a forward on a training view, and for a
        content-aware run whose textures have not started, of a training step once they have and of E's render of
        one view (None otherwise): the planner's texture-start jump and routine cost."""
        model, opt = self.model, self.opt
        try:
            self.model, self.opt = copy.deepcopy(model), copy.deepcopy(opt)
            step_s = self._time_steps(1)
            with torch.no_grad():
                render_s = _median_seconds(lambda: self.render_fn(self.model.render_inputs(),
                                                                   self.train_views[0].camera), device=self.device)
            textured_s = error_view_s = None
            if self.cfg.method == "content_aware" and not self.textures_started:
                self._start_textures()
                textured_s = self._time_steps(schedule.texture_start(self.cfg) + 1)
                error_view_s = _median_seconds(lambda: compute_E(self.model, self.train_views[:1], self.render_fn,
                                                                 self.cfg.lambda_ssim), device=self.device)
        finally:
            self.model, self.opt = model, opt
        return step_s, render_s, textured_s, error_view_s

    def _start_textures(self) -> None:
        """Allocate self.model's textures (the run's texture start; the calibration does it on its copy)."""
        cfg = self.cfg
        self.model.k_min = compute_k_min(self.model.means.detach(), self.cameras)
        texels.start_textures(self.model, self.opt, cfg.start_texels, cfg.min_t2p_exp, cfg.max_texture_res,
                              cfg.texture_alloc, cfg.texture_sigma)

    def _time_steps(self, it: int) -> float:
        """Median seconds of a training step of self.model on the first training view at iteration `it`'s learning
        rates (with a virtual_coverage term's share: one per virtual_every steps)."""
        view = self.train_views[0]
        lrs = schedule.learning_rates(self.cfg, it, self.extent, self.model.sh.shape[1], self.device)

        def step():
            for name in ALL_PARAMS:
                getattr(self.model, name).grad = None
            inputs = self.model.render_inputs()
            rgb, rasterized = self._training_render(inputs, view, None)
            training_loss(rgb, view.image_t, self.model, view.camera, self.cfg, rasterized=rasterized,
                          textures=inputs.textures).total.backward()
            self.opt.step(self.model, lrs)
            # as the loop does after every step: learning rates that make the copy diverge make the run diverge
            # (said as such, before a render of non-finite parameters fails on its input checks)
            self._check_finite(None)

        seconds = _median_seconds(step, device=self.device)
        if self.cfg.lambda_normal > 0:  # its share of the run's steps (from normal_from on)
            share = max(0.0, 1.0 - schedule.at(self.cfg, self.cfg.normal_from) / max(1, self.cfg.iterations))
            seconds += share * _median_seconds(lambda: normal_loss(self.model.render_inputs(), view.camera,
                                                                   self.cfg.backend).backward(), device=self.device)
        if self.virtual:
            seconds += (_median_seconds(lambda: self._virtual_step(self.cfg.virtual_every), device=self.device)
                        / self.cfg.virtual_every)
        return seconds

    @property
    def _shift(self) -> float:
        """The periodic calendar's phase shift: the budget planner's (moved by its re-plans), else 0."""
        return self.planner.shift if self.planner is not None else 0.0

    @property
    def _clock(self) -> BudgetPlanner | None:
        """The planner that observes the run's step, routine, evaluation and checkpoint times."""
        return self.planner or self.estimator

    def _plan_start(self) -> None:
        if self.estimator is not None:
            # (not in log.jsonl, which holds what the run did: the estimates are clock readings, in the summary)
            self.estimator.calibrate(*self._calibrate())
            return
        if self.planner is None:
            return
        if self.planner.plan.iterations == 0:  # a fresh run (a resumed one keeps its plan)
            self.cfg.iterations = self.planner.calibrate(*self._calibrate())
        plan = self.planner.plan
        self._log({"type": "plan", "it": self.it, "time_budget_s": plan.budget_s, "iterations": self.cfg.iterations,
                   "calibration_step_s": plan.calib_step_s, "calibration_render_s": plan.calib_render_s,
                   "calibration_textured_step_s": plan.calib_textured_step_s,
                   "budget_left_s": round(self.planner.budget_s_left(), 2)})

    def run(self):
        cfg = self.cfg
        if self.it == 0:
            self._log({"type": "start", "n": self.model.num_primitives, "method": cfg.method,
                       "device": str(self.device), "backend": cfg.backend, "pixels": self.pixels,
                       "coverage": round(self.coverage, 3), "max_primitives": cfg.max_primitives})
        self._plan_start()
        if self.planner is not None:
            yield Planned(self.it, cfg.iterations, self.planner.plan.budget_s)
        if self.estimator is not None:
            yield Estimated(self.it, cfg.iterations, self.estimator.estimates[0][1])
        while self.it < cfg.iterations:
            with self._whole_step():
                it, loss, terms, lrs, events = self._train_step(cfg)
            if it % cfg.log_every == 0 or it == 1:
                self._log({"type": "step", "it": it, "loss": float(loss.detach()), "l1": terms.l1, "ssim": terms.ssim,
                           "psnr": terms.psnr, "n": self.model.num_primitives, "texels": self.model.num_texels,
                           "sh_degree": self.model.sh_degree, "lr_pos": lrs["means"],
                           **({"normal": self.last_normal} if self._normal_active(it) else {}),
                           "seconds": round(self.train_seconds, 3), "wall": round(self.wall_seconds(), 3),
                           **self._device_memory()})
            yield Step(it, float(loss.detach()), terms.psnr, self.model.num_primitives, self.model.num_texels,
                       self.train_seconds)
            for ev in events:
                self._log({"type": "routine", "it": ev.it, "kind": ev.kind, **ev.stats,
                           "n": self.model.num_primitives, "texels": self.model.num_texels})
                yield ev
            if cfg.test_every and schedule.every(cfg, cfg.test_every, it, self._shift) and it < cfg.iterations:
                t0 = time.perf_counter()
                p, s = self.evaluate()
                if self._clock is not None:
                    self._clock.observe_eval(time.perf_counter() - t0, it)
                self._log({"type": "test", "it": it, "psnr": p, "ssim": s})
                yield Eval(it, p, s)
            if (cfg.checkpoint_every and schedule.every(cfg, cfg.checkpoint_every, it, self._shift)
                    and it < cfg.iterations):
                t0 = time.perf_counter()
                path = self._save_checkpoint()
                if self._clock is not None:
                    self._clock.observe_checkpoint(time.perf_counter() - t0)
                yield Checkpoint(it, path)
            if self.planner is not None:
                planned = self.planner.maybe_replan(it)
                if planned is not None and planned != cfg.iterations:
                    cfg.iterations = planned
                    self._log({"type": "plan", "it": it, "iterations": planned,
                               "budget_left_s": round(self.planner.budget_s_left(), 2)})
                    yield Planned(it, planned, self.planner.plan.budget_s)
            if self.estimator is not None and self.estimator.estimate_due(it):
                yield Estimated(it, cfg.iterations, self.estimator.observe_estimate(it))
        if cfg.method == "content_aware" and cfg.texture_trim > 0:
            # Model only what the textures hold: texels below texture_trim in every channel go (texels.trim;
            # idempotent, so a resumed run that trims again changes nothing).
            stats = texels.trim(self.model, self.opt, cfg.texture_trim)
            self._log({"type": "routine", "it": self.it, "kind": "trim", **stats, "n": self.model.num_primitives,
                       "texels": self.model.num_texels})
            yield Routine(self.it, "trim", stats)
        if (budget := size_budget.fit(self.model, self.opt, cfg, final=True)) is not None:
            self._log({"type": "routine", "it": self.it, "kind": "budget", **budget, "n": self.model.num_primitives,
                       "texels": self.model.num_texels})
            yield Routine(self.it, "budget", budget)
        if self.exposure is not None:
            gains = self.exposure.gains().detach().cpu()
            self._log({"type": "exposure", "it": self.it, "gains": {v.name: [round(float(x), 5) for x in gains[i]]
                                                                     for i, v in enumerate(self.train_views)}})
        p, s = self.evaluate()
        self._log({"type": "test", "it": self.it, "psnr": p, "ssim": s})
        yield Eval(self.it, p, s)
        self._save_checkpoint()
        summary = self._finish(p, s)
        yield Done(self.it, summary)

    def _train_step(self, cfg: TrainConfig):
        """One iteration: a random training view, loss, backward, Adam, then the schedule's routines (_adapt).
        Returns (iteration, loss, loss terms, learning rates, routine events)."""
        t0 = time.perf_counter()
        self.it += 1
        it = self.it
        self.model.sh_degree = schedule.sh_degree(cfg, it)
        view = self._next_view()
        # A random background colour per step (cfg.random_background) makes transparency unpredictable,
        # so coverage cannot stand in for dark colours; E, tests and exports use cfg.background.
        bg = torch.rand(3, generator=self.gen).to(self.device) if cfg.random_background else None
        inputs = self.model.render_inputs()
        rgb, rasterized = self._training_render(inputs, view, bg)
        if self.exposure is not None:
            rgb = self.exposure.apply(rgb, self.view_index[view.name])
        terms = training_loss(rgb, view.image_t, self.model, view.camera, cfg, rasterized=rasterized,
                              textures=inputs.textures)
        loss = terms.total
        if cfg.debug_nan_at and it == cfg.debug_nan_at:
            loss = loss * float("nan")  # testing hook for the NaN guard
        self._check_finite(loss)
        for name in ALL_PARAMS:
            getattr(self.model, name).grad = None
        loss.backward()
        if cfg.method != "content_aware" and it <= schedule.at(cfg, cfg.densify_until):
            self.acc.add_view(self.model.means, self.model.means.grad, view.camera)
        self._virtual_step(it)
        self._normal_step(it, view)
        lrs = schedule.learning_rates(cfg, it, self.extent, self.model.sh.shape[1], self.device)
        self.opt.step(self.model, lrs)
        if self.exposure is not None:
            self.exposure.step()
            if (cfg.exposure_check > 0 and not self.exposure.checked
                    and it >= max(1, round(cfg.exposure_check * cfg.iterations))):
                self._log({"type": "exposure_check", "it": it, **self.exposure.check(cfg.exposure_min_gain)})
        self._check_finite(loss.detach())
        t1 = time.perf_counter()
        events = list(self._adapt(it))
        if self.model.num_primitives == 0:
            self._no_primitives_left(events)
        t2 = time.perf_counter()
        self.train_seconds += t2 - t0
        if (clock := self._clock) is not None:
            clock.observe_step(t1 - t0, it)
            if any(ev.kind == "texture_start" for ev in events):
                clock.observe_texture_start(it)
            if any(ev.kind in ("full", "late") for ev in events):
                clock.observe_routine(t2 - t1, it)
        return it, loss, terms, lrs, events

    @contextlib.contextmanager
    def _whole_step(self):
        """Ctrl-C and SIGTERM (a cluster's time limit or preemption) wait for the step to end, then a checkpoint of
        that state is written before the stop goes on: `--resume` loses no step (the periodic checkpoint may be
        up to checkpoint_every iterations older)."""
        try:
            with atomic.signals_deferred():
                yield
        except (KeyboardInterrupt, Terminated):
            if self.it > 0:
                self._save_checkpoint()
            raise

    def _device_memory(self) -> dict:
        """{"cuda_peak_mb": peak memory torch's allocator has held on the training GPU so far} on CUDA, else {}
        (no synchronisation: the allocator's own counter)."""
        if self.device.type != "cuda":
            return {}
        return {"cuda_peak_mb": round(torch.cuda.max_memory_allocated(self.device) / 2**20, 1)}

    def _background_mask(self):
        """With init_shell: a function model -> [N] bool of the far primitives the split/upscale ranking leaves out."""
        if self.sphere is None:
            return None
        centre, reach = self.sphere
        return lambda model: far_mask(model.means, centre, reach)

    def _adapt(self, it: int):
        cfg, model, opt = self.cfg, self.model, self.opt
        if cfg.method == "content_aware":
            # --time-budget: not before the plan rests on measured steps (BudgetPlanner.measured_plan)
            if (not self.textures_started and it >= schedule.texture_start(cfg)
                    and (self.planner is None or self.planner.measured_plan)):
                self.textures_started = True
                self._start_textures()
                budget = size_budget.fit(model, opt, cfg)
                yield Routine(it, "texture_start", {"t2p_exp_mean": float(model.t2p_exp.float().mean()),
                                                    **(budget or {})})
            # Routines refine textures: none before they start (a --time-budget run holds its texture start until
            # the plan rests on measured steps, while a short first plan's calendar may already call for routines).
            kind = schedule.routine_kind(cfg, it, self._shift) if self.textures_started else None
            if kind == "full":
                # CTGS_LEAN_ROUTINE=0: the paper's order (the same final state; more transient texels, fewer ops;
                # on a GPU about the lean order's time, 1.5x its peak memory: docs/guide/gpu.md)
                lean = os.environ.get("CTGS_LEAN_ROUTINE", "1") != "0"
                gains = None
                if self.exposure is not None and cfg.exposure_in_E:
                    g = self.exposure.gains().detach()
                    gains = {v.name: g[i] for i, v in enumerate(self.train_views)}
                yield Routine(it, "full", full_routine(model, opt, cfg, it, self.train_views, self.render_fn,
                                                       self.cameras, self._background_mask(), lean=lean, gains=gains))
                if schedule.content_opacity_reset(cfg, it, self._shift):
                    value = max(2.0 * cfg.prune_opacity, RESET_OPACITY)  # prune_opacity = 0 would give 0
                    reset_opacity(model, opt, value)
                    yield Routine(it, "opacity_reset", {"value": value})
            elif kind == "late":
                yield Routine(it, "late", late_routine(model, opt, cfg, self.cameras))
            elif self.textures_started and schedule.every(cfg, cfg.realloc_every, it, self._shift):
                texels.realloc(model, opt, cfg.max_texture_res, cfg.texture_alloc, cfg.texture_sigma)
                if (budget := size_budget.fit(model, opt, cfg)) is not None:
                    yield Routine(it, "budget", budget)
            return
        # Baselines: 3DGS adaptive density control.
        if schedule.densify_active(cfg, it, self._shift):
            prune_big = it > schedule.at(cfg, cfg.opacity_reset_every)
            stats = densify_and_prune(model, opt, self.acc, cfg, self.extent, self.gen, prune_big)
            yield Routine(it, "densify", stats)
        if schedule.opacity_reset(cfg, it, self._shift):
            reset_opacity(model, opt)
            yield Routine(it, "opacity_reset", {})

    def _finish(self, test_psnr: float, test_ssim: float) -> dict:
        from ctgs.train.run import write_outputs

        return write_outputs(self, test_psnr, test_ssim)
