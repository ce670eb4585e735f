"""Training components: the features a config turns on, each called by the loop through the hooks of
ctgs.train.hooks with the run's TrainState and keeping its own state (the far shell's and the virtual views' are in
shell.py and virtual.py). `make_components` lists those of a run, in the order the loop calls them (after the
strategy)."""

from __future__ import annotations

import math

from ctgs.train.components.budget import SHARE, BudgetPlanner, median_seconds
from ctgs.train.components.exposure import Exposure
from ctgs.train.components.normal import geometry_terms
from ctgs.train.components.shell import Shell
from ctgs.train.components.virtual import VirtualCoverage
from ctgs.train.config import schedule
from ctgs.train.events import Estimated, Planned, Routine
from ctgs.train.hooks import Component
from ctgs.train.routines import size_budget


class NormalTerm(Component):
    """2DGS's geometric terms on the step's view, from one more render back-propagated on its own: lambda_normal x the
    depth-normal consistency from normal_from on, lambda_dist x the depth distortion from dist_from on; their last
    values go into the step's log record."""

    def __init__(self):
        self.last: dict = {}

    @staticmethod
    def active(cfg, it: int) -> dict:
        """{"normal": bool, "dist": bool}: which terms step `it` adds."""
        return {"normal": cfg.lambda_normal > 0 and it >= schedule.at_int(cfg, cfg.normal_from),
                "dist": cfg.lambda_dist > 0 and it >= schedule.at_int(cfg, cfg.dist_from)}

    def post_backward(self, st, it: int, view) -> None:
        on = self.active(st.cfg, it)
        if not any(on.values()):
            return
        terms = geometry_terms(st.model.render_inputs(), view.camera, st.cfg.backend, **on)
        weights = {"normal": st.cfg.lambda_normal, "dist": st.cfg.lambda_dist}
        total = sum(weights[k] * t for k, t in terms.items())
        self.last = {k: float(t.detach()) for k, t in terms.items()}
        if not all(math.isfinite(v) for v in self.last.values()):  # (parameters are scanned after the optimiser)
            st.check_finite(total)
        total.backward()

    def log_fields(self, st, it: int) -> dict:
        on = self.active(st.cfg, it)
        return {k: v for k, v in self.last.items() if on[k]}

    def step_seconds(self, st, view) -> float:
        cfg = st.cfg  # its share of the run's steps (from the earlier of the terms' starts on)
        starts = [schedule.at(cfg, f) for f, lam in ((cfg.normal_from, cfg.lambda_normal),
                                                     (cfg.dist_from, cfg.lambda_dist)) if lam > 0]
        share = max(0.0, 1.0 - min(starts, default=cfg.iterations) / max(1, cfg.iterations))
        both = {"normal": cfg.lambda_normal > 0, "dist": cfg.lambda_dist > 0}
        return share * median_seconds(
            lambda: sum(geometry_terms(st.model.render_inputs(), view.camera, cfg.backend, **both).values()).backward(),
            device=st.device)


class SizeBudget(Component):
    """max_params (--max-params, max_params_per_value): after the last iteration and the trim, textures coarsened until
    the model holds at most max_params, counted exactly (the strategy's routines keep it as they go)."""

    def finish(self, st):
        if (budget := size_budget.fit(st.model, st.opt, st.cfg, final=True)) is not None:
            yield Routine(st.it, "budget", budget)


class ExposureCompensation(Exposure, Component):
    """exposure_comp: a per-channel gain per training image on its training renders (components.exposure), stepped
    after the model's optimiser; exposure_check judges them once; the run's log ends with the learned gains."""

    def __init__(self, names: list[str], device, lr: float, channels):
        """names: the training views'; lr, channels: config lr_exposure, exposure_channels."""
        super().__init__(len(names), device, lr, channels)
        self.names = list(names)
        self.index = {name: i for i, name in enumerate(self.names)}

    def restore(self, st, saved: dict) -> None:
        if "exposure" in saved:
            self.load_state_dict(saved["exposure"])

    def checkpoint(self, st) -> dict:
        return {"exposure": self.state_dict()}

    def train_render(self, st, rgb, view):
        return self.apply(rgb, self.index[view.name])

    def post_step(self, st, it: int) -> None:
        self.step()
        cfg = st.cfg
        if cfg.exposure_in_E:  # the gains the routines' E takes (names in train_views' order: make_components)
            st.view_gains = self.gains().detach()
        if cfg.exposure_check > 0 and not self.checked and it >= max(1, round(cfg.exposure_check * cfg.iterations)):
            st.log({"type": "exposure_check", "it": it, **self.check(cfg.exposure_min_gain)})

    def finish(self, st):
        gains = self.gains().detach().cpu()
        st.log({"type": "exposure", "it": st.it, "gains": {name: [round(float(x), 5) for x in gains[i]]
                                                           for i, name in enumerate(self.names)}})
        return ()


class TimeBudget(Component):
    """--time-budget: the planner of the run's length (re-planned as it runs, with the periodic calendar's phase
    shift); a fresh run of fixed length: the same cost model estimating its wall time only (components.budget).
    Either observes the run's step, routine, evaluation and checkpoint times; a resumed fixed-length run has neither."""

    def __init__(self):
        self.planner = None
        self.estimator = None

    @property
    def clock(self) -> BudgetPlanner | None:
        return self.planner or self.estimator

    @property
    def shift(self) -> float:
        """The periodic calendar's phase shift: the planner's (moved by its re-plans), else 0."""
        return self.planner.shift if self.planner is not None else 0.0

    def admits(self, st, kind: str, it: int) -> bool:
        """A date of the `kind` calendar ("routine", "eval") at iteration `it`: kept, unless it would take that kind's
        wall seconds so far past its share of the run's (components.budget.SHARE; while none of that kind has taken any
        time, the first date, it is kept). A fixed-length run keeps every date. Asking changes nothing."""
        if self.planner is None or st.spent[kind] == 0.0:
            return True
        cost = self.planner.date_cost(kind, it)
        return st.spent[kind] + cost <= SHARE[kind] * (st.wall_seconds() + cost)

    @property
    def textures_may_start(self) -> bool:
        """Not before the plan rests on measured steps (BudgetPlanner.measured_plan)."""
        return self.planner is None or self.planner.measured_plan

    def _planner(self, st) -> BudgetPlanner:
        return BudgetPlanner(st.cfg, st.user_cfg.time_budget * 60.0, st.start_time - st.wall_before,
                             len(st.train_views), len(st.test_views))

    def initialize(self, st) -> None:
        if st.user_cfg.time_budget > 0:
            self.planner = self._planner(st)
        else:
            self.estimator = BudgetPlanner(st.cfg, None, st.start_time, len(st.train_views), len(st.test_views))

    def restore(self, st, saved: dict) -> None:
        if st.user_cfg.time_budget <= 0:
            return
        self.planner = self._planner(st)
        if "planner" in saved:
            self.planner.load_state_dict(saved["planner"])
            if st.textures_started and self.planner.tex_at is None:  # a checkpoint of an earlier planner
                self.planner.observe_texture_start(min(st.it, schedule.texture_start(st.cfg)))

    def checkpoint(self, st) -> dict:
        return {"planner": self.planner.state_dict()} if self.planner else {}

    def needs_first_plan(self) -> bool:
        """A fresh --time-budget run not yet planned."""
        return self.planner is not None and self.planner.plan.iterations == 0

    def needs_calibration(self) -> bool:
        """Whether `begin` plans or estimates from the loop's calibration (st.calibration): a fresh run's first plan or
        its fixed length's estimate."""
        return self.needs_first_plan() or self.estimator is not None

    def first_plan(self, st) -> int:
        """The planned iterations of a fresh --time-budget run, from st.calibration."""
        return self.planner.calibrate(*st.calibration)

    def begin(self, st):
        if self.estimator is not None:
            # (not in log.jsonl, which holds what the run did: the estimates are clock readings, in the summary)
            self.estimator.calibrate(*st.calibration)
            yield Estimated(st.it, st.cfg.iterations, self.estimator.estimates[0][1])
        if self.planner is None:
            return
        # a fresh run's plan (unless ctgs train made it before the run: Trainer.plan_now); a resumed run keeps its own
        iterations = self.first_plan(st) if self.needs_first_plan() else self.planner.plan.iterations
        plan = self.planner.plan
        st.log({"type": "plan", "it": st.it, "time_budget_s": plan.budget_s, "iterations": iterations,
                "calibration_step_s": plan.calib_step_s, "calibration_render_s": plan.calib_render_s,
                "calibration_textured_step_s": plan.calib_textured_step_s,
                "budget_left_s": round(self.planner.budget_s_left(), 2)})
        yield Planned(st.it, iterations, plan.budget_s)

    def timed_step(self, st, it: int, step_s: float, routine_s: float, events) -> None:
        if (clock := self.clock) is None:
            return
        clock.observe_step(step_s, it)
        if any(ev.kind == "texture_start" for ev in events):
            clock.observe_texture_start(it)
        if any(ev.kind in ("full", "late") for ev in events):
            clock.observe_routine(routine_s, it)

    def timed(self, st, what: str, seconds: float, it: int) -> None:
        if (clock := self.clock) is None:
            return
        if what == "eval":
            clock.observe_eval(seconds, it)
        else:
            clock.observe_checkpoint(seconds)

    def after_step(self, st, it: int):
        if self.planner is not None:
            planned = self.planner.maybe_replan(it)
            if planned is not None and planned != st.cfg.iterations:
                st.log({"type": "plan", "it": it, "iterations": planned,
                        "budget_left_s": round(self.planner.budget_s_left(), 2)})
                yield Planned(it, planned, self.planner.plan.budget_s)
        if self.estimator is not None and self.estimator.estimate_due(it):
            yield Estimated(it, st.cfg.iterations, self.estimator.observe_estimate(it))


def make_components(cfg, scene, train_views, device) -> list[Component]:
    """The components of a run of (resolved) config cfg, in calling order: the extra terms' gradients after the
    strategy's statistics (virtual views, then the normal term); at the end the size budget's fit, then the exposure
    gains' record."""
    parts = [Shell(scene, train_views, device) if cfg.init_shell > 0 else None,
             VirtualCoverage(cfg, scene, train_views, device) if cfg.virtual_coverage > 0 else None,
             NormalTerm() if cfg.lambda_normal > 0 or cfg.lambda_dist > 0 else None,
             SizeBudget() if cfg.max_params > 0 else None,
             ExposureCompensation([v.name for v in train_views], device, cfg.lr_exposure, cfg.exposure_channels)
             if cfg.exposure_comp else None,
             TimeBudget()]
    return [p for p in parts if p is not None]
