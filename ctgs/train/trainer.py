"""The training loop: one iteration = one random training view, loss, backward, Adam, schedule.

`Trainer.run()` is a generator of typed events (ctgs/train/events.py); it writes the JSON-lines log,
atomic checkpoints, and on success model.pt + train_summary.json into the run folder.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from ctgs import fused
from ctgs.errors import UserError
from ctgs.metrics.ssim import ssim
from ctgs.model.surfels import SurfelModel
from ctgs.train import checkpoint as ckpt
from ctgs.train import schedule, texels
from ctgs.train.adam import ALL_PARAMS, SurfelAdam
from ctgs.train.config import TrainConfig
from ctgs.train.densify import GradAccumulator, densify_and_prune, reset_opacity
from ctgs.train.events import Checkpoint, Done, Eval, Routine, Step
from ctgs.train.init import init_model
from ctgs.train.kmin import compute_k_min
from ctgs.train.loss import training_loss
from ctgs.train.routines import full_routine, late_routine


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


def machine_name() -> str:
    import platform

    return f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)"


class Trainer:
    def __init__(self, cfg: TrainConfig, scene, run_dir: str, resume: bool = False):
        self.cfg = cfg
        self.run_dir = run_dir
        self.device = pick_device(cfg)
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)  # OpenMP spin-waiting on an oversubscribed CPU costs ~5x
        if self.device.type == "cpu":
            fused.tune_allocator()  # freed [T, 3] temporaries are reused, not faulted in afresh
        self.extent = float(scene.extent)
        self.train_views = make_views(scene.train, self.device)
        self.test_views = make_views(scene.test, self.device)
        if not self.train_views:
            raise UserError(f"{scene.root}: no training images (check --images and holdout)")
        self.cameras = [v.camera for v in self.train_views]
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        os.makedirs(os.path.join(run_dir, "checkpoints"), exist_ok=True)
        self.log_path = os.path.join(run_dir, "log.jsonl")
        state = ckpt.load_checkpoint(run_dir) if resume else None
        if resume and state is None:
            raise UserError(f"{run_dir}: --resume but no checkpoint in checkpoints/; start without --resume")
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % 2**32)
        if state is None:
            mode = {"content_aware": "content_aware", "2dgs": "none", "fixed_texture": "fixed"}[cfg.method]
            self.model = init_model(scene.points, scene.point_colors, max_points=cfg.max_init_points,
                                    opacity=cfg.init_opacity, max_sh_degree=cfg.max_sh_degree,
                                    random_rotation=cfg.random_rotation, normals=cfg.init_normals, texture_mode=mode,
                                    fixed_res=cfg.fixed_texture_res, seed=cfg.seed)
            self._to_device()
            self.model.k_min = compute_k_min(self.model.means.detach(), self.cameras)
            self.opt = SurfelAdam(self.model, cfg.adam_eps)
            self.it = 0
            self.train_seconds = 0.0
            self.perm, self.perm_pos = None, 0
            self.acc = GradAccumulator(self.model.num_primitives, self.device)
            self.log_lines = 0
            open(self.log_path, "w").close()
        else:
            self._restore(state)

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
        self.train_seconds = float(state["train_seconds"])
        self.perm = state["perm"]
        self.perm_pos = int(state["perm_pos"])
        self.acc = GradAccumulator(self.model.num_primitives, self.device)
        self.acc.load_state_dict({k: v.to(self.device) for k, v in state["acc"].items()})
        ckpt.restore_rng(state["rng"], self.gen)
        # Drop log lines written after the checkpoint (they will be produced again).
        self.log_lines = int(state["log_lines"])
        lines = open(self.log_path).read().splitlines()[: self.log_lines] if os.path.exists(self.log_path) else []
        with open(self.log_path, "w") as fh:
            fh.write("".join(line + "\n" for line in lines))

    def _state(self) -> dict:
        return {"model": self.model.state_dict(), "opt": self.opt.state_dict(), "iteration": self.it,
                "train_seconds": self.train_seconds, "perm": self.perm, "perm_pos": self.perm_pos,
                "acc": {k: v.cpu() for k, v in self.acc.state_dict().items()}, "rng": ckpt.rng_state(self.gen),
                "log_lines": self.log_lines, "config": self.cfg.to_dict()}

    def _save_checkpoint(self) -> str:
        self._check_finite(None, full=True)
        path = ckpt.checkpoint_path(self.run_dir)
        ckpt.atomic_torch_save(self._state(), path)
        return path

    def _log(self, record: dict) -> None:
        with open(self.log_path, "a") as fh:
            fh.write(json.dumps(record) + "\n")
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

    # ---- loop ------------------------------------------------------------------------------------
    def run(self):
        cfg = self.cfg
        if self.it == 0:
            self._log({"type": "start", "n": self.model.num_primitives, "method": cfg.method,
                       "device": str(self.device), "backend": cfg.backend})
        while self.it < cfg.iterations:
            t0 = time.perf_counter()
            self.it += 1
            it = self.it
            self.model.sh_degree = schedule.sh_degree(cfg, it)
            view = self._next_view()
            # A random background colour per step (cfg.random_background) makes transparency unpredictable,
            # so coverage cannot stand in for dark colours; E, tests and exports use cfg.background.
            bg = torch.rand(3, generator=self.gen).to(self.device) if cfg.random_background else None
            out = self.render_fn(self.model.render_inputs(), view.camera, background=bg)
            terms = training_loss(out.rgb, view.image_t, self.model, view.camera, cfg)
            loss = terms.total
            if cfg.debug_nan_at and it == cfg.debug_nan_at:
                loss = loss * float("nan")  # testing hook for the NaN guard
            self._check_finite(loss)
            for name in ALL_PARAMS:
                getattr(self.model, name).grad = None
            loss.backward()
            if cfg.method != "content_aware" and it <= cfg.scaled(cfg.densify_until):
                self.acc.add_view(self.model.means, self.model.means.grad, view.camera)
            lrs = schedule.learning_rates(cfg, it, self.extent, self.model.sh.shape[1], self.device)
            self.opt.step(self.model, lrs)
            self._check_finite(loss.detach())
            events = list(self._adapt(it))
            self.train_seconds += time.perf_counter() - t0
            if it % cfg.log_every == 0 or it == 1:
                self._log({"type": "step", "it": it, "loss": float(loss.detach()), "l1": terms.l1, "ssim": terms.ssim,
                           "psnr": terms.psnr, "n": self.model.num_primitives, "texels": self.model.num_texels,
                           "sh_degree": self.model.sh_degree, "lr_pos": lrs["means"],
                           "seconds": round(self.train_seconds, 3)})
            yield Step(it, float(loss.detach()), terms.psnr, self.model.num_primitives, self.model.num_texels,
                       self.train_seconds)
            for ev in events:
                self._log({"type": "routine", "it": ev.it, "kind": ev.kind, **ev.stats,
                           "n": self.model.num_primitives, "texels": self.model.num_texels})
                yield ev
            if cfg.test_every and it % cfg.scaled(cfg.test_every) == 0 and it < cfg.iterations:
                p, s = self.evaluate()
                self._log({"type": "test", "it": it, "psnr": p, "ssim": s})
                yield Eval(it, p, s)
            if cfg.checkpoint_every and it % cfg.scaled(cfg.checkpoint_every) == 0 and it < cfg.iterations:
                yield Checkpoint(it, self._save_checkpoint())
        p, s = self.evaluate()
        self._log({"type": "test", "it": self.it, "psnr": p, "ssim": s})
        yield Eval(self.it, p, s)
        self._save_checkpoint()
        summary = self._finish(p, s)
        yield Done(self.it, summary)

    def _adapt(self, it: int):
        cfg, model, opt = self.cfg, self.model, self.opt
        if cfg.method == "content_aware":
            if it == schedule.texture_start(cfg):
                model.k_min = compute_k_min(model.means.detach(), self.cameras)
                texels.start_textures(model, opt, cfg.start_texels, cfg.min_t2p_exp, cfg.max_texture_res)
                yield Routine(it, "texture_start", {"t2p_exp_mean": float(model.t2p_exp.float().mean())})
            kind = schedule.routine_kind(cfg, it)
            if kind == "full":
                yield Routine(it, "full", full_routine(model, opt, cfg, it, self.train_views, self.render_fn,
                                                       self.cameras))
            elif kind == "late":
                yield Routine(it, "late", late_routine(model, opt, cfg, self.cameras))
            elif it > schedule.texture_start(cfg) and it % cfg.scaled(cfg.realloc_every) == 0:
                texels.realloc(model, opt, cfg.max_texture_res)
            return
        # Baselines: 3DGS adaptive density control.
        if cfg.scaled(cfg.densify_from) < it <= cfg.scaled(cfg.densify_until) and it % cfg.scaled(cfg.densify_every) == 0:
            prune_big = it > cfg.scaled(cfg.opacity_reset_every)
            stats = densify_and_prune(model, opt, self.acc, cfg, self.extent, self.gen, prune_big)
            yield Routine(it, "densify", stats)
        if it <= cfg.scaled(cfg.densify_until) and it % cfg.scaled(cfg.opacity_reset_every) == 0:
            reset_opacity(model, opt)
            yield Routine(it, "opacity_reset", {})

    def _finish(self, test_psnr: float, test_ssim: float) -> dict:
        from ctgs.train.run import write_outputs

        return write_outputs(self, test_psnr, test_ssim)
