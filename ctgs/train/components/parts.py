"""Training components: the features a config turns on, each called by the trainer through the hooks of
ctgs.train.hooks and keeping its own state. `make_components` lists those of a run, in the order the trainer calls
them (after the strategy)."""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from ctgs.errors import UserError
from ctgs.train.config import schedule
from ctgs.train.loop import calibration
from ctgs.train.routines import size_budget
from ctgs.train.components.budget import SHARE, BudgetPlanner
from ctgs.train.events import Estimated, Planned, Routine
from ctgs.train.components.exposure import Exposure
from ctgs.train.hooks import Component
from ctgs.train.components.normal import normal_loss
from ctgs.train.components.shell import composite, far_mask, open_mask, scene_sphere
from ctgs.train.components.virtual import coverage_loss, virtual_views


class Shell(Component):
    """init_shell: the sphere that tells the far shell's primitives (initial points: ctgs.train.start.init.scene_model) from
    the scene's; training renders composite the scene over them where the view sees past the SfM points (two renders:
    ctgs.train.components.shell), and the content-aware routines never split or upscale them."""

    def __init__(self, scene, train_views, device):
        self.sphere = scene_sphere(scene.points, scene.train)
        # per training view, the pixels where the shell may show in training renders
        self.open_px = {v.name: torch.from_numpy(open_mask(scene.points, v.camera)).to(device) for v in train_views}

    def far(self, model) -> torch.Tensor:
        """[N] bool: model's primitives on the far shell."""
        return far_mask(model.means, *self.sphere)

    def render(self, tr, inputs, view, bg):
        return composite(tr.render_fn, inputs, view.camera, self.far(tr.model), self.open_px[view.name],
                         tr.background if bg is None else bg)


class VirtualCoverage(Component):
    """virtual_coverage: virtual views half a camera step from each training camera, with the pixels the training
    cameras hold (ctgs.train.components.virtual), visited in a fixed shuffled cycle (resume-safe: by iteration)."""

    def __init__(self, cfg, scene, train_views, device):
        cameras = [v.camera for v in train_views]
        self.views = [replace(vv, camera=vv.camera.to(device), mask=vv.mask.to(device))
                      for vv in virtual_views([v.name for v in train_views], cameras, scene.points,
                                              pixels=cfg.virtual_pixels)]
        if not self.views:
            raise UserError(f"{scene.root}: virtual_coverage found no virtual view with {cfg.virtual_pixels} pixels "
                            "(it needs two training cameras with SfM points in view); set virtual_coverage = 0")
        self.order = torch.randperm(len(self.views), generator=torch.Generator().manual_seed(cfg.seed + 1))

    def post_backward(self, tr, it: int, view) -> None:
        """Every virtual_every-th step, one virtual view's coverage term, rendered and back-propagated on its own."""
        every = tr.cfg.virtual_every
        if it % every:
            return
        vv = self.views[int(self.order[(it // every) % len(self.views)])]
        alpha = tr.render_fn(tr.model.render_inputs(), vv.camera).alpha
        (tr.cfg.virtual_coverage * coverage_loss(alpha, vv)).backward()

    def step_seconds(self, tr, view) -> float:
        every = tr.cfg.virtual_every
        return calibration.median_seconds(lambda: self.post_backward(tr, every, view), device=tr.device) / every


class NormalTerm(Component):
    """lambda_normal: from normal_from on, 2DGS's depth-normal consistency term on the step's view, rendered and
    back-propagated on its own; its last value goes into the step's log record."""

    def __init__(self):
        self.last = float("nan")

    @staticmethod
    def active(cfg, it: int) -> bool:
        return it >= schedule.at_int(cfg, cfg.normal_from)

    def post_backward(self, tr, it: int, view) -> None:
        if not self.active(tr.cfg, it):
            return
        term = normal_loss(tr.model.render_inputs(), view.camera, tr.cfg.backend)
        self.last = float(term.detach())
        if not math.isfinite(self.last):  # (the parameters are scanned once per step, after the optimiser)
            tr._check_finite(term)
        (tr.cfg.lambda_normal * term).backward()

    def log_fields(self, tr, it: int) -> dict:
        return {"normal": self.last} if self.active(tr.cfg, it) else {}

    def step_seconds(self, tr, view) -> float:
        cfg = tr.cfg  # its share of the run's steps (from normal_from on)
        share = max(0.0, 1.0 - schedule.at(cfg, cfg.normal_from) / max(1, cfg.iterations))
        return share * calibration.median_seconds(
            lambda: normal_loss(tr.model.render_inputs(), view.camera, cfg.backend).backward(), device=tr.device)


class SizeBudget(Component):
    """max_params (--max-params, max_params_per_value): after the last iteration and the trim, textures coarsened until
    the model holds at most max_params, counted exactly (the strategy's routines keep it as they go)."""

    def finish(self, tr):
        if (budget := size_budget.fit(tr.model, tr.opt, tr.cfg, final=True)) is not None:
            yield Routine(tr.it, "budget", budget)


class ExposureCompensation(Exposure, Component):
    """exposure_comp: a per-channel gain per training image on its training renders (ctgs.train.components.exposure), stepped
    after the model's optimiser; exposure_check judges them once; the run's log ends with the learned gains."""

    def __init__(self, cfg, train_views, device):
        super().__init__(len(train_views), device, cfg.lr_exposure, cfg.exposure_channels)
        self.names = [v.name for v in train_views]
        self.index = {name: i for i, name in enumerate(self.names)}

    def view_gains(self) -> dict:
        """{training view name: its gain} (E with exposure_in_E)."""
        g = self.gains().detach()
        return {name: g[i] for i, name in enumerate(self.names)}

    def restore(self, tr, state: dict) -> None:
        if "exposure" in state:
            self.load_state_dict(state["exposure"])

    def checkpoint(self) -> dict:
        return {"exposure": self.state_dict()}

    def train_render(self, tr, rgb, view):
        return self.apply(rgb, self.index[view.name])

    def post_step(self, tr, it: int) -> None:
        self.step()
        cfg = tr.cfg
        if cfg.exposure_check > 0 and not self.checked and it >= max(1, round(cfg.exposure_check * cfg.iterations)):
            tr.log({"type": "exposure_check", "it": it, **self.check(cfg.exposure_min_gain)})

    def finish(self, tr):
        gains = self.gains().detach().cpu()
        tr.log({"type": "exposure", "it": tr.it, "gains": {name: [round(float(x), 5) for x in gains[i]]
                                                           for i, name in enumerate(self.names)}})
        return ()


class TimeBudget(Component):
    """--time-budget: the planner of the run's length (re-planned as it runs, with the periodic calendar's phase
    shift); a fresh run of fixed length: the same cost model estimating its wall time only (ctgs.train.components.budget).
    Either observes the run's step, routine, evaluation and checkpoint times; a resumed fixed-length run has neither."""

    def __init__(self):
        self.planner = None
        self.estimator = None
        self.last_kept: dict = {}  # {calendar kind: iteration of its last date kept} (admits)

    @property
    def clock(self) -> BudgetPlanner | None:
        return self.planner or self.estimator

    @property
    def shift(self) -> float:
        """The periodic calendar's phase shift: the planner's (moved by its re-plans), else 0."""
        return self.planner.shift if self.planner is not None else 0.0

    def admits(self, tr, kind: str, it: int) -> bool:
        """A date of the `kind` calendar ("routine", "eval") at iteration `it`: kept, unless it would take that kind's
        wall seconds so far past its share of the run's (ctgs.train.components.budget.SHARE; the first date of each kind is
        always kept). A fixed-length run keeps every date."""
        if self.planner is None or kind not in self.last_kept:
            self.last_kept[kind] = it
            return True
        cost = self.planner.date_cost(kind, it)
        if tr.spent[kind] + cost > SHARE[kind] * (tr.wall_seconds() + cost):
            return False
        self.last_kept[kind] = it
        return True

    @property
    def textures_may_start(self) -> bool:
        """Not before the plan rests on measured steps (BudgetPlanner.measured_plan)."""
        return self.planner is None or self.planner.measured_plan

    def _planner(self, tr) -> BudgetPlanner:
        return BudgetPlanner(tr.cfg, tr.user_cfg.time_budget * 60.0, tr.start_time - tr.wall_before,
                             len(tr.train_views), len(tr.test_views))

    def initialize(self, tr) -> None:
        if tr.user_cfg.time_budget > 0:
            self.planner = self._planner(tr)
        else:
            self.estimator = BudgetPlanner(tr.cfg, None, tr.start_time, len(tr.train_views), len(tr.test_views))

    def restore(self, tr, state: dict) -> None:
        if tr.user_cfg.time_budget <= 0:
            return
        self.planner = self._planner(tr)
        self.last_kept = dict(state.get("calendar_last_kept", {}))
        if "planner" in state:
            self.planner.load_state_dict(state["planner"])
            if tr.strategy.textures_started and self.planner.tex_at is None:  # a checkpoint of an earlier planner
                self.planner.observe_texture_start(min(tr.it, schedule.texture_start(tr.cfg)))

    def checkpoint(self) -> dict:
        return {"planner": self.planner.state_dict(), "calendar_last_kept": dict(self.last_kept)} if self.planner else {}

    def begin(self, tr):
        if self.estimator is not None:
            # (not in log.jsonl, which holds what the run did: the estimates are clock readings, in the summary)
            self.estimator.calibrate(*calibration.calibrate(tr))
            yield Estimated(tr.it, tr.cfg.iterations, self.estimator.estimates[0][1])
        if self.planner is None:
            return
        if self.planner.plan.iterations == 0:  # a fresh run (a resumed one keeps its plan)
            tr.cfg.iterations = self.planner.calibrate(*calibration.calibrate(tr))
        plan = self.planner.plan
        tr.log({"type": "plan", "it": tr.it, "time_budget_s": plan.budget_s, "iterations": tr.cfg.iterations,
                "calibration_step_s": plan.calib_step_s, "calibration_render_s": plan.calib_render_s,
                "calibration_textured_step_s": plan.calib_textured_step_s,
                "budget_left_s": round(self.planner.budget_s_left(), 2)})
        yield Planned(tr.it, tr.cfg.iterations, plan.budget_s)

    def timed_step(self, tr, it: int, step_s: float, routine_s: float, events) -> None:
        if (clock := self.clock) is None:
            return
        clock.observe_step(step_s, it)
        if any(ev.kind == "texture_start" for ev in events):
            clock.observe_texture_start(it)
        if any(ev.kind in ("full", "late") for ev in events):
            clock.observe_routine(routine_s, it)

    def timed(self, tr, what: str, seconds: float, it: int) -> None:
        if (clock := self.clock) is None:
            return
        if what == "eval":
            clock.observe_eval(seconds, it)
        else:
            clock.observe_checkpoint(seconds)

    def after_step(self, tr, it: int):
        if self.planner is not None:
            planned = self.planner.maybe_replan(it)
            if planned is not None and planned != tr.cfg.iterations:
                tr.cfg.iterations = planned
                tr.log({"type": "plan", "it": it, "iterations": planned,
                        "budget_left_s": round(self.planner.budget_s_left(), 2)})
                yield Planned(it, planned, self.planner.plan.budget_s)
        if self.estimator is not None and self.estimator.estimate_due(it):
            yield Estimated(it, tr.cfg.iterations, self.estimator.observe_estimate(it))


def make_components(tr, scene) -> list[Component]:
    """The components of tr's run, in calling order: the extra terms' gradients after the strategy's statistics
    (virtual views, then the normal term); at the end the size budget's fit, then the exposure gains' record."""
    cfg = tr.cfg
    parts = [Shell(scene, tr.train_views, tr.device) if cfg.init_shell > 0 else None,
             VirtualCoverage(cfg, scene, tr.train_views, tr.device) if cfg.virtual_coverage > 0 else None,
             NormalTerm() if cfg.lambda_normal > 0 else None,
             SizeBudget() if cfg.max_params > 0 else None,
             ExposureCompensation(cfg, tr.train_views, tr.device) if cfg.exposure_comp else None,
             TimeBudget()]
    return [p for p in parts if p is not None]
