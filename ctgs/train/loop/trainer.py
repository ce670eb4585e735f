"""The training loop: one iteration = one random training view, loss, backward, Adam, schedule.

`Trainer.run()` is a generator of typed events (ctgs/train/events.py); it writes the JSON-lines log,
atomic checkpoints, and on success model.pt + train_summary.json into the run folder. What changes the model
besides the loss's gradient is the run's strategy (ctgs.train.strategies, by config `method`) and its components
(ctgs.train.components), called through the hooks of ctgs.train.hooks with the run's TrainState (`Trainer.state`:
the model, its optimiser, the config, the views and counters), never with the trainer.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import numpy as np
import torch

from ctgs.errors import Terminated, UserError
from ctgs.io import atomic
from ctgs.io.signals import signals_deferred
from ctgs.metrics.lpips import load_lpips, lpips_hwc
from ctgs.metrics.ssim import ssim
from ctgs.model.extent import active_texels
from ctgs.model.surfels import SurfelModel
from ctgs.ops import fused
from ctgs.runs import checkpoint as ckpt
from ctgs.train.components import ExposureCompensation, Shell, TimeBudget, make_components
from ctgs.train.config import TrainConfig, rules, schedule
from ctgs.train.events import Checkpoint, Done, Eval, Planned, Step
from ctgs.train.hooks import TrainState, TrainView
from ctgs.train.loop import calibration
from ctgs.train.loop.summary import write_outputs
from ctgs.train.routines.kmin import compute_k_min, view_coverage
from ctgs.train.start.init import scene_model
from ctgs.train.step.adam import ALL_PARAMS, SurfelAdam
from ctgs.train.step.loss import masked, recomposited, training_loss
from ctgs.train.strategies import make_strategy


# What the run's wall time went to besides its steps (train_summary.json "seconds_in"): full and late routines,
# reallocations and texture starts ("routine"), periodic test evaluations ("eval"), checkpoints ("checkpoint").
SPENT_KINDS = ("routine", "eval", "checkpoint")


class TrainingDiverged(UserError):
    """NaN/Inf in the loss or the parameters: training stopped, the last checkpoint is kept."""

    exit_code = 4


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
        extra = [None if x is None else torch.from_numpy(np.ascontiguousarray(x)).reshape(*x.shape[:2], 1).to(device)
                 for x in (getattr(v, "mask", None), getattr(v, "alpha", None))]
        out.append(TrainView(v.name, v.camera.to(device), torch.from_numpy(np.ascontiguousarray(v.image)).to(device),
                             *extra))
    return out


def observed_values(train_views) -> int:
    """Values a model is fitted to: RGB of every training pixel."""
    return int(sum(3 * v.camera.width * v.camera.height for v in train_views))


def _to_device(model: SurfelModel, device: torch.device) -> None:
    for name in ALL_PARAMS:
        setattr(model, name, getattr(model, name).detach().to(device).requires_grad_(True))
    for name in ("k_min", "t2p_exp", "tex_res", "tex_offset"):
        setattr(model, name, getattr(model, name).to(device))


def device_memory(device: torch.device) -> dict:
    """{"cuda_peak_mb": peak memory torch's allocator has held on the training GPU so far} on CUDA, else {}
    (no synchronisation: the allocator's own counter)."""
    if device.type != "cuda":
        return {}
    return {"cuda_peak_mb": round(torch.cuda.max_memory_allocated(device) / 2**20, 1)}


class Trainer:
    """cfg: the config as given (saved with the run); self.cfg is its copy resolved for this scene's image size
    (ctgs/train/config/rules.py) whose `iterations` is the planned run length (`--time-budget` re-plans it).
    start_time: time.monotonic() when the command started (the time budget counts from there).
    self.parts: the strategy, then the components (ctgs.train.hooks), in the order their hooks are called; each is
    called with self.state, the run's TrainState (the model, its optimiser, the config, views and counters), which
    holds what the trainer's model, opt, it, cfg, spent and clock attributes read."""

    def __init__(self, cfg: TrainConfig, scene, run_dir: str, resume: bool = False, start_time: float | None = None):
        self.run_dir = run_dir
        self.saved_at: float | None = None  # the clock's checkpoints: when the last was written, or the first step ended
        device = pick_device(cfg)
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)  # OpenMP spin-waiting on an oversubscribed CPU costs ~5x
        if device.type == "cpu":
            fused.tune_allocator()  # freed [T, 3] temporaries are reused, not faulted in afresh
        self.near = float(scene.train[0].camera.near) if scene.train else None  # the scene's (loader.near_plane)
        self.num_sfm_points = len(scene.points)
        self.world_origin = [float(x) for x in getattr(scene, "origin", (0.0, 0.0, 0.0))]  # saved with the model
        self.test_names = scene.meta.get("test_names")  # the scene's listed test views (test_views.txt), else None
        train_views = make_views(scene.train, device)
        test_views = make_views(scene.test, device)
        if not train_views:
            raise UserError(f"{scene.root}: no training images (check --images and holdout)")
        cameras = [v.camera for v in train_views]
        self.pixels = float(np.median([v.camera.width * v.camera.height for v in train_views]))
        # views' worth of scene in the capture (the primitive cap is per pixel of a typical view: config.rules)
        self.coverage = (view_coverage(torch.from_numpy(np.asarray(scene.points, np.float32)), cameras)
                         if rules.primitives_per_pixel(cfg) > 0 else 1.0)
        # the config resolved for the scene (max_params_per_value: the size budget from the observed values, an
        # explicit max_params wins) and the cap on the initial points
        resolved, init_cap = rules.for_scene(cfg, observed_values(train_views), self.pixels, self.coverage)
        self.strategy = make_strategy(cfg.method)
        self.parts = [self.strategy, *make_components(resolved, scene, train_views, device)]
        self.exposure, self.time = self.part(ExposureCompensation), self.part(TimeBudget)
        shell = self.part(Shell)
        self.last_routines_s = 0.0  # wall seconds of the last step's routines (their log records)
        self.state = TrainState(
            cfg=resolved, user_cfg=cfg, device=device, train_views=train_views, test_views=test_views,
            extent=float(scene.extent), background=torch.tensor(cfg.background, dtype=torch.float32, device=device),
            gen=torch.Generator().manual_seed(cfg.seed), log=self.log, check_finite=self._check_finite,
            start_time=time.monotonic() if start_time is None else start_time,
            far_sphere=None if shell is None else shell.sphere)
        os.makedirs(os.path.join(run_dir, "checkpoints"), exist_ok=True)
        self.log_path = os.path.join(run_dir, "log.jsonl")
        saved = ckpt.load_checkpoint(run_dir) if resume else None
        if resume and saved is None:
            raise UserError(f"{run_dir}: --resume but no checkpoint in checkpoints/; start without --resume")
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % 2**32)
        if saved is None:
            self._start(scene_model(scene, cfg, init_cap, self.strategy.texture_mode))
        else:
            self._restore(saved)

    def part(self, kind: type):
        """The run's part of that class, or None."""
        return next((p for p in self.parts if isinstance(p, kind)), None)

    # What the loop, its progress display and the summary read of the run: the state's.
    model = property(lambda self: self.state.model)
    opt = property(lambda self: self.state.opt)
    it = property(lambda self: self.state.it)
    cfg = property(lambda self: self.state.cfg)
    user_cfg = property(lambda self: self.state.user_cfg)
    device = property(lambda self: self.state.device)
    train_views = property(lambda self: self.state.train_views)
    test_views = property(lambda self: self.state.test_views)
    cameras = property(lambda self: self.state.cameras)
    extent = property(lambda self: self.state.extent)
    background = property(lambda self: self.state.background)
    gen = property(lambda self: self.state.gen)
    spent = property(lambda self: self.state.spent)
    start_time = property(lambda self: self.state.start_time)
    wall_before = property(lambda self: self.state.wall_before)

    # ---- state -----------------------------------------------------------------------------------
    def _start(self, model: SurfelModel) -> None:
        """A fresh run from `model` (the scene's initial surfels, start.init.scene_model)."""
        st = self.state
        st.model = model
        _to_device(st.model, st.device)
        st.model.k_min = compute_k_min(st.model.means.detach(), st.cameras)
        st.opt = SurfelAdam(st.model, st.cfg.adam_eps)
        st.it, self.train_seconds, self.perm, self.perm_pos, self.log_lines, self.saved_it = 0, 0.0, None, 0, 0, 0
        st.spent = dict.fromkeys(SPENT_KINDS, 0.0)
        for part in self.parts:
            part.initialize(st)
        open(self.log_path, "w").close()

    def _restore(self, saved: dict) -> None:
        st = self.state
        st.model = SurfelModel.from_state_dict(saved["model"], st.device)
        _to_device(st.model, st.device)
        st.opt = SurfelAdam(st.model, st.cfg.adam_eps)
        st.opt.load_state_dict(saved["opt"], st.device)
        st.it = self.saved_it = int(saved["iteration"])  # the checkpoint it resumes from is saved
        st.cfg.iterations = int(saved.get("planned_iterations", st.cfg.iterations))
        st.wall_before = float(saved.get("wall_seconds", 0.0))
        self.train_seconds = float(saved["train_seconds"])
        st.spent = dict.fromkeys(SPENT_KINDS, 0.0) | saved.get("spent", {})  # older checkpoints: not counted
        self.perm, self.perm_pos = saved["perm"], int(saved["perm_pos"])
        for part in self.parts:
            part.restore(st, saved)
        ckpt.restore_rng(saved["rng"], st.gen)
        self.log_lines = ckpt.cut_log(self.log_path, int(saved["log_lines"]))

    def _state(self) -> dict:
        st = self.state
        saved = {"model": st.model.state_dict(), "opt": st.opt.state_dict(), "iteration": st.it,
                 "train_seconds": self.train_seconds, "perm": self.perm, "perm_pos": self.perm_pos,
                 "rng": ckpt.rng_state(st.gen), "log_lines": self.log_lines, "config": st.user_cfg.to_dict(),
                 "planned_iterations": st.cfg.iterations, "wall_seconds": self.wall_seconds(),
                 "spent": dict(st.spent)}
        for part in self.parts:
            saved.update(part.checkpoint(st))
        return saved

    def observed_values(self) -> int:
        """Values the model is fitted to: RGB of every training pixel."""
        return observed_values(self.train_views)

    def wall_seconds(self) -> float:
        """Wall-clock seconds of this run so far, earlier sessions included."""
        return self.state.wall_seconds()

    def _save_checkpoint(self) -> str:
        self._check_finite(None, full=True)
        path = ckpt.save_checkpoint(self.run_dir, self._state())  # the one before stays as prev.pt
        self.saved_it = self.it
        self.saved_at = time.monotonic()
        return path

    def checkpoint_on_stop(self) -> None:
        """Ctrl-C or SIGTERM that landed between two steps (a log line, an evaluation, the progress display): the
        last step is whole, and is checkpointed unless it already is (a stop during a step is, by _whole_step)."""
        if self.it > self.saved_it:
            self._save_checkpoint()

    def log(self, record: dict) -> None:
        atomic.append_text(self.log_path, json.dumps(record) + "\n")  # a full disk: OSError naming the log
        self.log_lines += 1

    # ---- rendering -------------------------------------------------------------------------------
    def render_fn(self, inputs, camera, error_image=None, background=None, backward_stats=None):
        return self.state.render_fn(inputs, camera, error_image, background, backward_stats)

    def _next_view(self) -> TrainView:
        if self.perm is None or self.perm_pos >= len(self.perm):
            self.perm = torch.randperm(len(self.train_views), generator=self.gen).tolist()
            self.perm_pos = 0
        v = self.train_views[self.perm[self.perm_pos]]
        self.perm_pos += 1
        return v

    @torch.no_grad()
    def evaluate(self) -> tuple[float, float, float | None]:
        """Mean PSNR / SSIM over the test views (train views if there are none), and LPIPS when cfg.test_lpips
        asks for it and its weights are present (else None)."""
        views = self.test_views or self.train_views
        inputs = self.model.render_inputs()
        net = load_lpips(device=self.device)[0] if self.cfg.test_lpips else None
        psnrs, ssims, lp = [], [], []
        for v in views:
            rgb, gt = masked(self.render_fn(inputs, v.camera).rgb.clamp(0, 1), v.image_t, v.mask_t)
            used = 1.0 if v.mask_t is None else float(v.mask_t.float().mean())  # MSE over the pixels in use
            mse = ((rgb - gt) ** 2).mean().div(used).clamp_min(1e-12)
            psnrs.append(float(-10 * torch.log10(mse)))
            ssims.append(float(ssim(rgb, gt)))
            if net is not None:
                lp.append(lpips_hwc(net, rgb, gt))
        return float(np.mean(psnrs)), float(np.mean(ssims)), (float(np.mean(lp)) if lp else None)

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
                if name in names and p.numel() and (name in self.opt.nonfinite or not fused.all_finite(p)):
                    bad = f"parameter {name}"
                    break
        if bad is None:
            return
        hint = ckpt.rerun_hint(self.run_dir)
        self.log({"type": "diverged", "it": self.it, "what": bad})
        raise TrainingDiverged(f"{self.run_dir}: NaN/Inf in {bad} at iteration {self.it}; {hint}")

    def _no_primitives_left(self, events) -> None:
        """The routines removed every primitive: say so (a NaN loss on an empty model would blame the lrs)."""
        kind = events[-1].kind if events else "a"
        self.log({"type": "diverged", "it": self.it, "what": "no primitives left"})
        raise TrainingDiverged(
            f"{self.run_dir}: the {kind} routine at iteration {self.it} pruned every primitive "
            f"({self.strategy.prune_rules}), nothing is left to train; the run started from {self.num_sfm_points} SfM "
            f"points: too few points, points outside the cameras' views or images that do not belong to the model end "
            f"this way: check the scene (`ctgs sfm` writes a report) and --images")

    # ---- loop ------------------------------------------------------------------------------------
    def training_render(self, inputs, view, bg, backward_stats=None):
        """(rgb, rasterized) of a training step over `bg` (None: cfg.background): one render, or a part's (init_shell:
        the scene composited over the far primitives where the view sees past the SfM points, two renders).
        backward_stats: filled by the plain render's backward (ctgs.render.BackwardStats)."""
        for part in self.parts:
            if (out := part.render(self.state, inputs, view, bg)) is not None:
                return out
        out = self.render_fn(inputs, view.camera, background=bg, backward_stats=backward_stats)
        return out.rgb, out.rasterized

    def run(self):
        cfg, st = self.cfg, self.state
        if self.it == 0:
            self.log({"type": "start", "n": self.model.num_primitives, "method": cfg.method,
                      "device": str(self.device), "backend": cfg.backend, "pixels": self.pixels,
                      "coverage": round(self.coverage, 3), "max_primitives": cfg.max_primitives})
        if self.time.needs_calibration():
            st.calibration = calibration.calibrate(self)
        for part in self.parts:
            yield from self._applied(part.begin(st))
        self._take_decisions()
        while self.it < cfg.iterations:
            with self._whole_step():
                it, loss, terms, lrs, events = self._train_step(cfg)
            if it % cfg.log_every == 0 or it == 1:
                self.log({"type": "step", "it": it, "loss": float(loss.detach()), "l1": terms.l1, "ssim": terms.ssim,
                          "psnr": terms.psnr, "n": self.model.num_primitives, "texels": self.model.num_texels,
                          "sh_degree": self.model.sh_degree, "lr_pos": lrs["means"],
                          **{k: v for part in self.parts for k, v in part.log_fields(st, it).items()},
                          "seconds": round(self.train_seconds, 3), "wall": round(self.wall_seconds(), 3),
                          **device_memory(self.device)})
            yield Step(it, float(loss.detach()), terms.psnr, self.model.num_primitives, self.model.num_texels,
                       self.train_seconds)
            yield from self._logged(events)
            # scored before the step at each test multiple, where routines and opacity resets fall (after one: ~14 dB)
            if self._due(cfg.test_every, it + 1) and self.time.admits(st, "eval", it + 1):
                yield self._evaluation(it, timed=True)
            if self._due(cfg.checkpoint_every, it) or self._checkpoint_late(it):
                t0 = time.perf_counter()
                path = self._save_checkpoint()
                self._timed("checkpoint", time.perf_counter() - t0, it)
                yield Checkpoint(it, path)
            for part in self.parts:
                yield from self._applied(part.after_step(st, it))
            self._take_decisions()
        for part in self.parts:
            t0 = time.perf_counter()
            events = list(part.finish(st))
            self.last_routines_s = time.perf_counter() - t0
            yield from self._logged(events)
        final = self._evaluation(self.it)
        yield final
        self._save_checkpoint()
        yield Done(self.it, write_outputs(self, final.test_psnr, final.test_ssim))

    def _applied(self, events):
        """Pass on a part's run events, taking a new plan's length into the config (the time budget's Planned)."""
        for ev in events:
            if isinstance(ev, Planned):
                self.state.cfg.iterations = ev.iterations
            yield ev

    def _take_decisions(self) -> None:
        """The time budget's calendar decisions, handed to the parts as the state's values."""
        self.state.shift = self.time.shift
        self.state.textures_may_start = self.time.textures_may_start

    def plan_now(self) -> int | None:
        """A fresh --time-budget run's first plan, made now on a calibration of a copy of the model (ctgs train's choice
        of method), instead of at the first step, which then logs it; the planned iterations, or None for a run without
        a budget or already planned."""
        if not self.time.needs_first_plan():
            return None
        self.state.calibration = calibration.calibrate(self)
        self.state.cfg.iterations = self.time.first_plan(self.state)
        return self.state.cfg.iterations

    def _due(self, paper_period: float, it: int) -> bool:
        """A periodic evaluation or checkpoint at `it` (none at the last iteration: the run's end has its own)."""
        return bool(paper_period) and schedule.every(self.cfg, paper_period, it, self.state.shift) \
            and it < self.cfg.iterations

    def _checkpoint_late(self, it: int) -> bool:
        """A checkpoint by the clock: the first once checkpoint_first_s of training have passed (counted from this
        session's first step: not the start-up, an extension build included), then one whenever checkpoint_every_s
        have passed since the last, so that a kill -9 loses at most that much training."""
        if self.saved_at is None:
            self.saved_at = time.monotonic()
            return False
        first = self.cfg.checkpoint_first_s if self.saved_it == 0 else 0.0
        limits = [s for s in (first, self.cfg.checkpoint_every_s) if s > 0]
        return bool(limits) and time.monotonic() - self.saved_at >= min(limits) and it < self.cfg.iterations

    def _timed(self, what: str, seconds: float, it: int) -> None:
        self.spent[what] += seconds
        for part in self.parts:
            part.timed(self.state, what, seconds, it)

    def _evaluation(self, it: int, timed: bool = False) -> Eval:
        t0 = time.perf_counter()
        p, s, lp = self.evaluate()
        if timed:
            self._timed("eval", time.perf_counter() - t0, it)
        self.log({"type": "test", "it": it, "psnr": p, "ssim": s, **({"lpips": lp} if lp is not None else {}),
                  **({"texels_active": active_texels(self.model)} if self.model.num_texels else {})})
        return Eval(it, p, s)

    def _logged(self, events):
        """Log and pass on routine events."""
        for ev in events:
            self.log({"type": "routine", "it": ev.it, "kind": ev.kind, **ev.stats, "n": self.model.num_primitives,
                      "texels": self.model.num_texels, "step_routines_s": round(self.last_routines_s, 4)})
            yield ev

    def _train_step(self, cfg: TrainConfig):
        """One iteration: a random training view, loss, backward, Adam, then the strategy's routines (_adapt).
        Returns (iteration, loss, loss terms, learning rates, routine events)."""
        t0 = time.perf_counter()
        st = self.state
        st.it += 1
        it = st.it
        self.model.sh_degree = schedule.sh_degree(cfg, it)
        view = self._next_view()
        # A random background colour per step (cfg.random_background) makes transparency unpredictable,
        # so coverage cannot stand in for dark colours; E, tests and exports use cfg.background.
        bg = torch.rand(3, generator=self.gen).to(self.device) if cfg.random_background else None
        inputs = self.model.render_inputs()
        stats = self.strategy.step_stats(st)  # error_from_steps: the backward sums the loss's error image
        rgb, rasterized = self.training_render(inputs, view, bg, stats)
        for part in self.parts:
            rgb = part.train_render(st, rgb, view)
        gt = view.image_t if bg is None else recomposited(view.image_t, view.alpha_t, self.background, bg)
        terms = training_loss(*masked(rgb, gt, view.mask_t), self.model, view.camera, cfg, rasterized=rasterized,
                              textures=inputs.textures, want_error=stats is not None)
        if stats is not None:
            stats.error_image = terms.error_image
        loss = terms.total
        if cfg.debug_nan_at and it == cfg.debug_nan_at:
            loss = loss * float("nan")  # testing hook for the NaN guard
        self._check_finite(loss)
        for name in ALL_PARAMS:
            getattr(self.model, name).grad = None
        loss.backward()
        for part in self.parts:
            part.post_backward(st, it, view)
        lrs = schedule.learning_rates(cfg, it, self.extent, self.model.sh.shape[1], self.device)
        self.opt.step(self.model, lrs)
        for part in self.parts:
            part.post_step(st, it)
        self._check_finite(loss.detach())
        t1 = time.perf_counter()
        events = list(self._adapt(it))
        if self.model.num_primitives == 0:
            self._no_primitives_left(events)
        t2 = time.perf_counter()
        self.train_seconds += t2 - t0
        self.last_routines_s = t2 - t1
        if events:
            self.spent["routine"] += t2 - t1
        for part in self.parts:
            part.timed_step(st, it, t1 - t0, t2 - t1, events)
        return it, loss, terms, lrs, events

    def _adapt(self, it: int):
        """The routines of iteration `it` (the strategy's step_end), with the time budget's word on a full-routine date
        at `it` (asked only where the calendar has one: a kept date is counted against the routines' share)."""
        st = self.state
        st.routine_kept = (not st.textures_started or schedule.routine_kind(st.cfg, it, st.shift) != "full"
                           or self.time.admits(st, "routine", it))
        for part in self.parts:
            yield from part.step_end(st, it)

    @contextlib.contextmanager
    def _whole_step(self):
        """Ctrl-C and SIGTERM (a cluster's time limit or preemption) wait for the step to end, then a checkpoint of
        that state is written before the stop goes on: `--resume` loses no step (the periodic checkpoint may be
        up to checkpoint_every iterations older)."""
        try:
            with signals_deferred():
                yield
        except (KeyboardInterrupt, Terminated):
            if self.it > 0:
                self._save_checkpoint()
            raise
