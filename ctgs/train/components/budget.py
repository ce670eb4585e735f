"""`--time-budget`: plan the iteration count so the whole `ctgs train` run ends within a wall-clock budget.

A schedule is a fraction of the run (ctgs/train/config/schedule.py), so the planner only has to choose the run
length N, and may change it while training: every event stays at its fraction of the (new) run.

Cost model (seconds, wall clock):
    T(N) = sum over the remaining iterations of b * g(it, N)          (training steps)
         + routines left(N) * t_routine + test evaluations left(N) * t_eval + checkpoints left(N) * t_ckpt
         + t_final                                                     (final evaluation and save)
g is a growth profile: the cost of one iteration grows while the model grows and is flat afterwards.
Baselines: g = 1 + (G - 1) * ramp over the densification window. Content-aware: g = 1 until the texture
start, then J * (1 + (R - 1) * ramp) over the routine window: starting the textures multiplies the step cost
by J at once (medians 2.1-2.7 per image size and preset in the herzjesu25 and demo runs' logs), and splits and
upscales grow it by R afterwards. Before the first step a calibration times, on a copy of the initial
model, a training step (forward+backward and Adam), a forward on a training view, and for content-aware
runs a training step with the textures started: J is measured on this machine at this image size, R is a
prior. b, the cost per unit of g, is an average of the measured steps divided by their g, so the known
jump at the texture start does not read as a change of machine speed; a wrong prior R only matters until
the model stops growing.
"""

from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ctgs.train.config import TrainConfig, schedule

# Growth of the per-iteration cost, per method: for the baselines from the start to the end of the
# densification window (2dgs: last tenth of a run / first 5% in the 2-core VM's logs, 2.6 demo, 2.1-4.5
# herzjesu25 images_8, 2.3-3.5 at 384 and 768 px); for content-aware runs from just after the texture start
# to the end of the routine window (R; the jump at the texture start is calibrated). R in the logs of the
# herzjesu25 runs: `fast` 1.46 (192 px, median of 27 runs), 1.58 (384 px, 55 runs), 2.16 (768 px, 3 runs);
# `balanced` 2.0 (192 px) and 2.7 (384 px); demo 1.1. A prior only: the cost is re-fitted at every re-plan.
# An earlier content-aware prior was a growth of 2.5 from the *untextured* calibration step, which
# left out the jump: the first plans of `--time-budget` runs were 2.6-3.2x the iterations run (384 px
# `balanced` and 768 px `fast`); see benchmarks/results/archive/budget_first_plan/708b530.md.
GROWTH_PRIOR = {"content_aware": 2.0, "2dgs": 3.0, "fixed_texture": 4.0}
# The texture start's jump, when the calibration did not measure it (a run resumed from an older checkpoint).
TEXTURE_JUMP_PRIOR = 2.4
REPLAN_FRACTION = 0.01  # re-plan every 1% of the planned run ...
REPLAN_MIN_ITERS = 10  # ... but not more often than every 10 iterations
SAFETY = 0.97  # plan for 97% of the budget: the rest absorbs the error of the last predictions
# The cost per unit of g is a trimmed mean of the last RECENT_STEPS measured steps: the slowest and the fastest TRIM
# of them left out. A plain average (earlier: an exponential one, time constant ~100 steps) lets a few slow steps move
# the plan: the first textured steps of a large texture start (first-touch allocation, 2.7M texels on a 135x240
# capture) read as the machine's speed cut a 10-minute plan from 469 to 29 iterations, and the run ended after 54 s.
# The trimmed mean ignores such steps, is about as steady as the average under a shared machine's bursts
# (tests/train/test_budget.py), and follows a lasting change of speed within a window.
RECENT_STEPS = 151
TRIM = 0.25
# Between two re-plans the number of iterations left changes by at most this factor, either way: a plan cannot
# collapse (or balloon) on one re-plan's evidence; re-plans every 1% of the run still follow a real change.
MAX_SWING = 2.0
# A run ends in the last END_SLACK of its budget: at the end of its plan with more left, it re-plans at once.
END_SLACK = 0.05
# The shortest run any preset makes (`preview`): below it no recorded run says what the model is worth.
SHORTEST_MEASURED = 1000
# The schedule dates full routines (E over up to error_views training views, splits, texel rescaling) and test
# evaluations at fractions of the run, so a run holds as many of them whatever its length: a short plan (a small
# budget, a busy machine) packs them into less time. On a bonsai252 run at 200x133 given 10 minutes on a machine slowed
# 2.3x, 31 routines came every 6-8 iterations, took most of the budget, and the run ended after 238 iterations at
# 18.1 dB. A budgeted run keeps each kind within its share of the time its steps take: where the dates at the
# schedule's fractions would cost more, only every k-th is kept (the calendar's stride k, re-chosen at every re-plan;
# a fixed-length run keeps every date).
SHARE = {"routine": 0.15, "eval": 0.05}


def _trimmed_mean(values) -> float:
    """Mean of `values` without their lowest and highest TRIM (all of them when there are fewer than 5)."""
    v = sorted(values)
    cut = int(len(v) * TRIM) if len(v) >= 5 else 0
    kept = v[cut:len(v) - cut]
    return float(sum(kept) / len(kept))


def short_plan_warning(iterations: int, budget_s: float, step_s: float, pixels: float) -> str | None:
    """One line for a plan shorter than any measured run (None otherwise): what the budget buys and the fixes."""
    if iterations >= SHORTEST_MEASURED:
        return None
    budget = f"{budget_s / 60:.1f} min" if budget_s >= 60 else f"{budget_s:.0f} s"
    return (f"ctgs train: warning: {budget} buys about {iterations} iteration{'s' if iterations != 1 else ''} here "
            f"by the first plan ({step_s:.2f} s per step at {pixels / 1e3:.0f}k pixels per view, timed on a copy of "
            f"the model: a busy machine makes it low; the run re-plans every 1%), fewer than `preview`'s "
            f"{SHORTEST_MEASURED}, the shortest run measured: expect a model far from trained. Give more minutes, "
            f"or train a smaller --images folder (a step costs about in proportion to the pixels; `ctgs sfm` "
            f"writes images_2, images_4 and images_8)")


# Passes over the training views (iterations / views) below which the content-aware method's textures had not paid
# for their cost in any run measured at equal time on a CPU against the 2DGS baseline (at 2DGS's own prune threshold):
# bonsai252 at 200x133 (220 views), `fast` for 15 minutes, about 25 passes: 1.21 dB below; herzjesu25 at 384x256 (21
# views), 10 minutes, about 100 passes: 0.13 dB below; bonsai252 at 399x266, 60 minutes, about 29 passes: 0.95 dB
# below. Above it: herzjesu25, 20 minutes, about 230 passes: 0.75 dB ahead (2 of 3 seeds). At equal iterations `paper`
# leads 2DGS* (bonsai252, 30k iterations: +0.17 dB): the CPU's minutes, not the method, are short.
# docs/guide/training.md, "When textures pay".
FEW_PASSES = 150


def few_passes_note(method: str, iterations: int, views: int) -> str | None:
    """One line for a content-aware run whose plan makes few passes over its training views (None otherwise)."""
    if method != "content_aware" or views <= 0 or iterations <= 0:
        return None
    passes = iterations / views
    if passes >= FEW_PASSES:
        return None
    count = f"{passes:.0f} passes" if passes >= 10 else f"{passes:.1f} passes" if passes != 1 else "1 pass"
    return (f"ctgs train: note: {iterations} iterations are {count} over the {views} training views; "
            f"below about {FEW_PASSES} the textures had not paid for their cost in the CPU runs measured against "
            f"the 2dgs baseline given the same minutes (bonsai252, 25 passes: 1.21 dB below; herzjesu25, 100 "
            f"passes: 0.13 dB below). More minutes, a smaller --images folder, or --config 2dgs may serve this "
            f"capture better "
            f"(docs/guide/training.md, \"When textures pay\")")


LONG_RUN_S = 3600.0  # a fixed run estimated longer than this is told how to take less


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min" if seconds < 90 * 60 else f"{seconds / 3600:.1f} h"


def estimate_line(it: int, iterations: int, wall_s: float) -> str:
    """What a fixed-length run is told of its wall time: first from the calibration, then from measured steps."""
    if it == 0:
        line = (f"about {_duration(wall_s)} for {iterations} iterations on this machine (timed on the initial model; "
                "re-estimated from the first measured steps)")
        if wall_s > LONG_RUN_S:
            line += ("; to take less: --time-budget MINUTES plans the run to fit, or train a smaller --images folder "
                     "(a step costs about in proportion to the pixels)")
        return line
    return f"about {_duration(wall_s)} for {iterations} iterations (re-estimated at iteration {it} from measured steps)"


@dataclass
class Plan:
    """What the planner chose (logged and written to train_summary.json)."""

    budget_s: float
    initial_iterations: int = 0
    iterations: int = 0
    calib_step_s: float = 0.0  # forward+backward of the initial model
    calib_render_s: float = 0.0  # forward only (E, evaluation)
    calib_textured_step_s: float = 0.0  # content-aware: a training step with the textures started (0: not measured)
    calib_error_view_s: float = 0.0  # content-aware: E's render of one view with the textures started (0: not measured)
    replans: int = 0
    history: list = field(default_factory=list)  # (it, planned N, predicted end s) at a few points


class BudgetPlanner:
    """Plans a `--time-budget` run's length; with budget_s None (a run of fixed length) it only estimates: the same
    calibration and cost model say how long the run will take (`estimate_s`): at the start, from REPLAN_MIN_ITERS
    measured steps, then every 1% of the run; the run's length and schedule are the config's (nothing re-planned,
    the texture start at its iteration)."""

    def __init__(self, cfg: TrainConfig, budget_s: float | None, start_time: float, n_train: int, n_test: int):
        self.cfg = cfg
        self.fixed = budget_s is None
        self.plan = Plan(budget_s=0.0 if budget_s is None else budget_s)
        # fixed runs: (iteration, predicted wall seconds of the whole run), the first at iteration 0
        self.estimates: list = []
        self.start = start_time  # time.monotonic() when the command started
        self.n_train, self.n_test = n_train, max(n_test, 0)
        self.growth = GROWTH_PRIOR.get(cfg.method, 2.5)
        self.jump = TEXTURE_JUMP_PRIOR if cfg.method == "content_aware" else 1.0
        self.tex_at: int | None = None  # iteration after which the textures started (None: not yet)
        self.base = 0.0  # recent seconds per training step per unit of g (without routines, evals, checkpoints)
        self.recent: collections.deque = collections.deque(maxlen=RECENT_STEPS)  # the last steps' seconds per g
        self.n_obs = 0  # steps observed
        self.n_obs_planned = 0  # steps observed when the plan was last made
        # Routines' and evaluations' seconds per unit of g: the calibration's forward renders until one is measured
        # (meanwhile scaled by measured step / calibrated step, the machine's speed against the calibration's).
        self.t_routine = 0.0
        self.t_eval = 0.0
        self.routine_seen = self.eval_seen = False
        self.base_calib = 0.0
        self.t_ckpt = 0.0
        self.t_save = 0.0
        self.last_replan = 0
        # The periodic calendar's phase shift (ctgs.train.config.schedule.every): moved at each re-plan that changes the
        # length, so routines, evaluations and checkpoints keep their spacing; 0 for a run that is never re-planned.
        self.shift = 0.0
        # Stride of the routine and evaluation calendars (SHARE): 1 keeps every date; set by each plan.
        self.stride = {kind: 1 for kind in SHARE}
        self._window_cache: tuple = (None, None)

    # ---- measurements ------------------------------------------------------------------------------
    def calibrate(self, step_s: float, render_s: float, textured_step_s: float | None = None,
                  error_view_s: float | None = None) -> int:
        """Initial plan from the timed training step (step_s) and forward (render_s) of the initial model and, for
        a content-aware run, its training step with the textures started (textured_step_s) and E's render of one
        view with them (error_view_s)."""
        self.plan.calib_step_s, self.plan.calib_render_s = step_s, render_s
        if textured_step_s and self.cfg.method == "content_aware":
            self.plan.calib_textured_step_s = textured_step_s
            self.jump = max(textured_step_s / max(step_s, 1e-12), 1.0)
        self.base = self.base_calib = step_s
        e_views = min(self.n_train, self.cfg.error_views) if self.cfg.error_views > 0 else self.n_train
        if error_view_s and self.cfg.method == "content_aware":
            # E's render measured with the textures started: per unit of g (the prediction multiplies by the jump,
            # which is the training step's, forward and backward: a forward alone grows less with the textures).
            # The guess below (two plain forwards per view, times the jump and the growth) put a routine of a
            # bonsai252 run (64 views at 200x133) at about 58 s where one took about 13 s: the plan of 900 s was 14
            # iterations, and the first routines, an evaluation and the texture start came at that plan's fractions.
            self.plan.calib_error_view_s = error_view_s
            self.t_routine = e_views * error_view_s / (self.jump if self.plan.calib_textured_step_s else 1.0)
        else:
            # E: a render with error statistics per view it uses (about two plain forwards' cost)
            self.t_routine = 2 * e_views * render_s
        self.t_eval = max(self.n_test, 1) * render_s
        self.t_ckpt = 0.05
        self.t_save = 0.2
        if self.fixed:
            self.plan.initial_iterations = self.plan.iterations = self.cfg.iterations
            self.observe_estimate(0)
            return self.cfg.iterations
        n = self._solve(0)
        self.stride = self._strides(0, n)
        self.plan.initial_iterations = self.plan.iterations = n
        self.plan.history.append((0, n, round(self.budget_s_left(), 1)))
        return n

    def observe_step(self, seconds: float, it: int) -> None:
        """A training step `it` took `seconds`. The calibration (timed on a copy of the model, possibly while the
        machine is busy with something else: at 768x512 beside another training compiling its extension it read
        2.2x the real step) stands for the step cost only until steps are measured; then the cost is the mean of the
        last RECENT_STEPS measured steps (per unit of g), their slowest and fastest TRIM left out."""
        self.recent.append(seconds / self._g_now(it))
        self.n_obs += 1
        self.base = _trimmed_mean(self.recent)

    def tex_pending(self) -> bool:
        return self.cfg.method == "content_aware" and self.tex_at is None

    @property
    def measured_plan(self) -> bool:
        """The plan was made from REPLAN_MIN_ITERS measured steps at least. A content-aware run starts its
        textures only then: the texture start cannot be undone, and a calibration on a busy machine can plan a
        few hundred iterations where the run gets a thousand (its fraction of the run: a handful of steps)."""
        return self.fixed or self.n_obs_planned >= REPLAN_MIN_ITERS

    # ---- fixed runs: the estimate ------------------------------------------------------------------
    def estimate_s(self, it: int) -> float:
        """Predicted wall seconds of the whole run (command start to outputs written), at iteration `it`."""
        return (time.monotonic() - self.start) + self._predict(it, self.plan.iterations)

    def estimate_due(self, it: int) -> bool:
        """A fixed run's next estimate: the first from REPLAN_MIN_ITERS measured steps (a content-aware run's after
        its texture start: before it, the jump is the calibration's), then every 1% of the run (as a budget's
        re-plans), which keeps the progress display's time left on the cost model."""
        if not self.fixed or not self.estimates or it >= self.plan.iterations:
            return False
        if len(self.estimates) == 1:
            if self.cfg.method == "content_aware":
                return self.tex_at is not None and it - self.tex_at >= REPLAN_MIN_ITERS
            return self.n_obs >= REPLAN_MIN_ITERS
        return it - self.estimates[-1][0] >= max(REPLAN_MIN_ITERS, int(REPLAN_FRACTION * self.plan.iterations))

    def observe_estimate(self, it: int) -> float:
        """Record and return the estimate at iteration `it` (the calibration's at 0; later, when estimate_due says)."""
        s = self.estimate_s(it)
        if len(self.estimates) < 200:
            self.estimates.append((it, round(s, 1)))
        return s

    def observe_texture_start(self, it: int) -> None:
        """The textures started after step `it` (steps after it pay the jump J). Where the jump is the prior's (not
        measured), the step window restarts: the true jump shows as a new cost per unit of g, which the untextured
        steps would otherwise outvote for a whole window. A measured jump keeps the window, so the first textured
        steps (first touches of the new texels, textures at their largest until the first routine) stay a minority
        the trimmed mean leaves out."""
        self.tex_at = it
        if self.recent and not self.plan.calib_textured_step_s:
            self.recent = collections.deque([self.base], maxlen=RECENT_STEPS)

    def observe_routine(self, seconds: float, it: int) -> None:
        self.t_routine = seconds / self._g_now(it)
        self.routine_seen = True

    def observe_eval(self, seconds: float, it: int) -> None:
        self.t_eval = seconds / self._g_now(it)
        self.eval_seen = True

    def _g_now(self, it: int) -> float:
        n = max(self.plan.iterations, it, 1)
        return self._g(it, n, self._window(n))

    def observe_checkpoint(self, seconds: float) -> None:
        self.t_ckpt = seconds

    def budget_s_left(self) -> float:
        return self.plan.budget_s - (time.monotonic() - self.start)

    # ---- planning ----------------------------------------------------------------------------------
    def maybe_replan(self, it: int) -> int | None:
        """New planned iteration count, or None when it is not time to re-plan (never for a fixed run)."""
        n = self.plan.iterations
        if self.fixed:
            return None
        # At the end of the plan with more than END_SLACK of the budget left: re-plan now (the run would end early).
        ending = it >= n - 1 and self.budget_s_left() > END_SLACK * self.plan.budget_s
        if it >= n and not ending:
            return None
        # Also on the step before the texture start: it cannot be undone, so it happens at its fraction of a
        # plan made from measured steps, not of the calibration's alone (a short plan starts it in a few steps).
        before_tex = self.tex_pending() and it + 1 >= schedule.texture_start(self.cfg)
        # Until the textures start: every REPLAN_MIN_ITERS steps (the first measured steps correct the calibration).
        every = REPLAN_MIN_ITERS if self.tex_pending() else max(REPLAN_MIN_ITERS, int(REPLAN_FRACTION * n))
        if it - self.last_replan < every and not before_tex and not ending:
            return None
        self.last_replan = it
        first = self.n_obs_planned == 0  # the first plan from measured steps corrects the calibration's freely
        self.n_obs_planned = self.n_obs
        new = self._solve(it)
        if not first:
            # bounded swing of the iterations left (at least one more step while the budget lasts)
            left = max(n - it, 1)
            new = min(max(new, it + max(1, math.ceil(left / MAX_SWING))), it + max(1, math.floor(left * MAX_SWING)))
        self.stride = self._strides(it, new)
        self.plan.replans += 1
        if new != n and len(self.plan.history) < 200:
            self.plan.history.append((it, new, round(self.budget_s_left(), 1)))
        if new != n and self.cfg.schedule_scale <= 0:
            # Keep the periodic calendar's phase (it + shift) / period continuous: every period scales by new / n.
            self.shift = schedule.replanned_shift(self.shift, it, n, new)
        self.plan.iterations = new
        return new

    def _growth_window(self, c: TrainConfig) -> tuple[float, float]:
        """Fractions of the run over which the model grows."""
        if c.method == "content_aware":
            start, end = schedule.routine_window(c)
        else:
            start, end = schedule.at(c, c.densify_from), schedule.at(c, c.densify_until)
        n = max(c.iterations, 1)
        return start / n, max(end / n, start / n + 1e-6)

    def _window(self, n: int) -> tuple[float, float]:
        """The growth window of a run of n iterations (cached: observe_step asks at every step)."""
        if self._window_cache[0] != n:
            self._window_cache = (n, self._growth_window(replace(self.cfg, iterations=n)))
        return self._window_cache[1]

    def _g(self, it: float, n: int, window: tuple[float, float]) -> float:
        """Cost of step `it` of a run of n iterations, in units of the initial model's step."""
        a, b = window
        p = it / n
        g = 1.0 + (self.growth - 1.0) * min(max((p - a) / (b - a), 0.0), 1.0)
        if self.cfg.method != "content_aware":
            return g
        textured = it > self.tex_at if self.tex_at is not None else p > a
        return self.jump * g if textured else 1.0

    def date_cost(self, kind: str, it: int) -> float:
        """Predicted wall seconds of a routine or periodic evaluation ("routine", "eval") at iteration `it`."""
        speed = self.base / self.base_calib if self.base_calib > 0 else 1.0
        seen, cost = (self.routine_seen, self.t_routine) if kind == "routine" else (self.eval_seen, self.t_eval)
        return cost * (1.0 if seen else speed) * self._g_now(it)

    def _costs(self, it: int, n: int) -> tuple[float, dict]:
        """(seconds from now to the end of a run of n iterations, at iteration `it` now, without its routines and
        periodic evaluations; {kind: those seconds at every date of the schedule's calendar})."""
        c = replace(self.cfg, iterations=n)
        window = self._growth_window(c)
        # Training steps: midpoint rule over 64 slices of the remaining run.
        steps, k = n - it, 64
        total = 0.0
        for j in range(k):
            total += self.base * self._g(it + (j + 0.5) * steps / k, n, window) * steps / k
        # routines, evaluations: their last measured (or calibrated) cost per unit of g, at the run's end growth
        g_late = self._g(n, n, window)
        speed = self.base / self.base_calib if self.base_calib > 0 else 1.0
        t_routine = self.t_routine * (1.0 if self.routine_seen else speed)
        t_eval = self.t_eval * (1.0 if self.eval_seen else speed)
        dated = {"routine": self._count_routines(c, it, n) * t_routine * g_late,
                 "eval": self._count(c, c.test_every, it, n - 1) * t_eval * g_late if c.test_every else 0.0}
        if c.checkpoint_every:
            total += self._count(c, c.checkpoint_every, it, n - 1) * self.t_ckpt
        total += t_eval * g_late + self.t_save  # final evaluation and outputs
        return total, dated

    def _strides(self, it: int, n: int, costs: tuple | None = None) -> dict:
        """{kind: the smallest calendar stride k that keeps that kind's dates within its SHARE of the time the rest of
        a run of n iterations takes} (1 everywhere for a fixed-length run)."""
        if self.fixed:
            return {kind: 1 for kind in SHARE}
        rest, dated = costs if costs is not None else self._costs(it, n)
        return {kind: max(1, math.ceil(dated[kind] * (1 - share) / (share * max(rest, 1e-9)) - 1e-9))
                for kind, share in SHARE.items()}

    def _predict(self, it: int, n: int) -> float:
        """Seconds from now to the end of a run of n iterations (at iteration `it` now), its routine and evaluation
        calendars thinned to their shares (_strides)."""
        rest, dated = costs = self._costs(it, n)
        strides = self._strides(it, n, costs)
        return rest + sum(dated[kind] / strides[kind] for kind in dated)

    @staticmethod
    def _count(c: TrainConfig, paper_period: float, lo: int, hi: int) -> int:
        """Multiples of the scaled period in (lo, hi] (the calendar's phase shift left out: at most one event of each
        kind off, which the next re-plan's measured costs absorb)."""
        if hi <= lo:
            return 0
        period = schedule.at(c, paper_period)
        if period <= 1:
            return hi - lo
        return max(0, math.floor(hi / period + 1e-9) - math.floor(lo / period + 1e-9))

    def _count_routines(self, c: TrainConfig, it: int, n: int) -> int:
        """Full routines left (E over the views: the routine's cost). The late downscales after the routine window
        render nothing (a pass over the textures): their cost is left to the measured steps."""
        if c.method != "content_aware":
            return 0
        start, end = schedule.routine_window(c)
        return self._count(c, c.routine_every, max(it, start - 1), min(end, n - 1))

    def _solve(self, it: int) -> int:
        """The largest n (> it) whose predicted end fits SAFETY x the budget left."""
        left = self.budget_s_left() * SAFETY
        lo = it + 1
        if self._predict(it, lo) >= left:
            return lo
        hi = max(lo + 1, 2 * self.plan.iterations if self.plan.iterations else 1000)
        while self._predict(it, hi) < left and hi < 10_000_000:
            lo, hi = hi, hi * 2
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if self._predict(it, mid) < left:
                lo = mid
            else:
                hi = mid
        return lo

    def summary(self) -> dict:
        p = self.plan
        if self.fixed:
            return {"estimated_wall_s": [s for _, s in self.estimates], "estimated_at_it": [i for i, _ in self.estimates]}
        return {"time_budget_s": p.budget_s, "planned_iterations_initial": p.initial_iterations,
                "calibration_step_s": round(p.calib_step_s, 5), "calibration_render_s": round(p.calib_render_s, 5),
                "calibration_textured_step_s": round(p.calib_textured_step_s, 5),
                "calibration_error_view_s": round(p.calib_error_view_s, 5),
                "texture_jump": round(self.jump, 3) if self.cfg.method == "content_aware" else None,
                # where the textures started, and where the schedule puts them (texture_start / 30000 of the run):
                # the start is fixed early from the speed measured then, so a load on the machine during the
                # first minute moves it (docs/guide/training.md)
                "texture_start_it": self.tex_at,
                "texture_start_scheduled_fraction": (round(self.cfg.texture_start / schedule.PAPER_ITERATIONS, 5)
                                                     if self.cfg.method == "content_aware"
                                                     and self.cfg.schedule_scale <= 0 else None),
                "replans": p.replans, "plan_history": p.history, "calendar_stride": dict(self.stride)}

    def state_dict(self) -> dict:
        return {"plan": vars(self.plan).copy(), "growth": self.growth, "base": self.base, "recent": list(self.recent),
                "jump": self.jump,
                "tex_at": self.tex_at, "n_obs": self.n_obs, "n_obs_planned": self.n_obs_planned,
                "t_routine": self.t_routine, "t_eval": self.t_eval, "routine_seen": self.routine_seen,
                "eval_seen": self.eval_seen, "base_calib": self.base_calib, "t_ckpt": self.t_ckpt, "t_save": self.t_save,
                "last_replan": self.last_replan, "shift": self.shift, "stride": dict(self.stride)}

    def load_state_dict(self, state: dict) -> None:
        self.plan = Plan(**state["plan"])
        self.growth = state["growth"]
        self.base = state.get("base", state.get("c_step", 0.0))  # c_step: checkpoints of an earlier planner
        # older checkpoints kept an average, not the steps: the window restarts from it
        self.recent = collections.deque(state.get("recent") or [self.base], maxlen=RECENT_STEPS)
        self.jump, self.tex_at = state.get("jump", self.jump), state.get("tex_at")
        self.n_obs = state.get("n_obs", 10_000)  # older checkpoints: long past the calibration
        self.n_obs_planned = state.get("n_obs_planned", self.n_obs)
        # older checkpoints: routine and eval costs as measured, not per unit of g (close enough late in a run)
        self.routine_seen, self.eval_seen = state.get("routine_seen", True), state.get("eval_seen", True)
        self.base_calib = state.get("base_calib", self.base)
        self.t_routine, self.t_eval, self.t_ckpt, self.t_save = (state[k] for k in ("t_routine", "t_eval", "t_ckpt",
                                                                                      "t_save"))
        self.last_replan = state["last_replan"]
        self.shift = state.get("shift", 0.0)  # older checkpoints: the calendar had no phase shift
        self.stride = {kind: 1 for kind in SHARE} | state.get("stride", {})  # older checkpoints: every date kept


def median_seconds(fn, reps: int = 3, device: torch.device | None = None) -> float:
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
