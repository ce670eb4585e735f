"""`--time-budget`: plan the iteration count so the whole `ctgs train` run ends within a wall-clock budget.

A schedule is a fraction of the run (ctgs/train/schedule.py), so the planner only has to choose the run
length N, and may change it while training: every event stays at its fraction of the (new) run.

Cost model (seconds, wall clock):
    T(N) = sum over the remaining iterations of c * g(it / N)         (training steps)
         + routines left(N) * t_routine + test evaluations left(N) * t_eval + checkpoints left(N) * t_ckpt
         + t_final                                                     (final evaluation and save)
g is a growth profile: the cost of one iteration grows while the model grows (textures start, splits,
densification) and is flat afterwards: g(p) = 1 + (G - 1) * ramp(p) over the growth window. c is
re-fitted to the measured recent cost whenever the planner re-plans, so a wrong prior G only matters
until the model stops growing. Before the first step a calibration times a forward+backward and a
forward of the initial model on a training view (this machine, this image size).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

from ctgs.train import schedule
from ctgs.train.config import TrainConfig

# Measured growth of the per-iteration cost from the start to the end of the growth window, per method
# (seconds per iteration over the last tenth of a run / over its first 5%, from the runs' log.jsonl on the
# 2-core VM after the CPU speed work: 2dgs 2.6 demo, 2.1-4.5 herzjesu25 images_8 (median of the four runs 3.2);
# content-aware 1.1-2.2). A prior only: c is re-fitted at every re-plan, so the prior matters until the model
# stops growing. 2dgs was 2.0 until those runs showed its plans shrinking mid-run (4733 -> 2948 iterations).
GROWTH_PRIOR = {"content_aware": 2.5, "2dgs": 3.0, "fixed_texture": 4.0}
REPLAN_FRACTION = 0.01  # re-plan every 1% of the planned run ...
REPLAN_MIN_ITERS = 10  # ... but not more often than every 10 iterations
SAFETY = 0.97  # plan for 97% of the budget: the rest absorbs the error of the last predictions
# Exponential average of the recent cost per iteration (weight of the previous value): a time constant of ~100
# steps. At 0.9 (10 steps) the plan followed the load of a shared machine burst by burst: a 45-minute herzjesu25
# run re-planned 17.0k -> 26.8k -> 17.7k iterations within 450 iterations, moving every schedule fraction with it.
# In tests/train/test_budget.py's simulation with step times noisy by ~30% per 10 steps, 0.99 cut the summed
# plan changes 3.5x (largest single change 49% -> 12%) and still ended within 0.2% of the budget, also with the
# machine turning 3x slower at 95% of the budget (ends at 1.006x).
RECENT = 0.99
# The shortest run any preset makes (`preview`): below it no recorded run says what the model is worth.
SHORTEST_MEASURED = 1000


def short_plan_warning(iterations: int, budget_s: float, step_s: float, pixels: float) -> str | None:
    """One line for a plan shorter than any measured run (None otherwise): what the budget buys and the fixes."""
    if iterations >= SHORTEST_MEASURED:
        return None
    budget = f"{budget_s / 60:.1f} min" if budget_s >= 60 else f"{budget_s:.0f} s"
    return (f"ctgs train: warning: {budget} buys about {iterations} iteration{'s' if iterations != 1 else ''} here "
            f"({step_s:.2f} s per step at {pixels / 1e3:.0f}k pixels per view), fewer than `preview`'s "
            f"{SHORTEST_MEASURED}, the shortest run measured: expect a model far from trained. Give more minutes, "
            f"or train a smaller --images folder (a step costs about in proportion to the pixels; `ctgs sfm` "
            f"writes images_2, images_4 and images_8)")


@dataclass
class Plan:
    """What the planner chose (logged and written to train_summary.json)."""

    budget_s: float
    initial_iterations: int = 0
    iterations: int = 0
    calib_step_s: float = 0.0  # forward+backward of the initial model
    calib_render_s: float = 0.0  # forward only (E, evaluation)
    replans: int = 0
    history: list = field(default_factory=list)  # (it, planned N, predicted end s) at a few points


class BudgetPlanner:
    def __init__(self, cfg: TrainConfig, budget_s: float, start_time: float, n_train: int, n_test: int):
        self.cfg = cfg
        self.plan = Plan(budget_s=budget_s)
        self.start = start_time  # time.monotonic() when the command started
        self.n_train, self.n_test = n_train, max(n_test, 0)
        self.growth = GROWTH_PRIOR.get(cfg.method, 2.5)
        self.c_step = 0.0  # recent seconds per training step (without routines, evals, checkpoints)
        self.t_routine = 0.0
        self.t_eval = 0.0
        self.t_ckpt = 0.0
        self.t_save = 0.0
        self.last_replan = 0

    # ---- measurements ------------------------------------------------------------------------------
    def calibrate(self, step_s: float, render_s: float) -> int:
        """Initial plan from one timed forward+backward (step_s) and forward (render_s) of the initial model."""
        self.plan.calib_step_s, self.plan.calib_render_s = step_s, render_s
        self.c_step = step_s
        self.t_routine = 2 * self.n_train * render_s  # E: a render and an error-statistics render per view
        self.t_eval = max(self.n_test, 1) * render_s
        self.t_ckpt = 0.05
        self.t_save = 0.2
        n = self._solve(0)
        self.plan.initial_iterations = self.plan.iterations = n
        self.plan.history.append((0, n, round(self.budget_s_left(), 1)))
        return n

    def observe_step(self, seconds: float) -> None:
        self.c_step = seconds if self.c_step <= 0 else RECENT * self.c_step + (1 - RECENT) * seconds

    def observe_routine(self, seconds: float) -> None:
        self.t_routine = seconds

    def observe_eval(self, seconds: float) -> None:
        self.t_eval = seconds

    def observe_checkpoint(self, seconds: float) -> None:
        self.t_ckpt = seconds

    def budget_s_left(self) -> float:
        return self.plan.budget_s - (time.monotonic() - self.start)

    # ---- planning ----------------------------------------------------------------------------------
    def maybe_replan(self, it: int) -> int | None:
        """New planned iteration count, or None when it is not time to re-plan."""
        n = self.plan.iterations
        if it - self.last_replan < max(REPLAN_MIN_ITERS, int(REPLAN_FRACTION * n)) or it >= n:
            return None
        self.last_replan = it
        new = self._solve(it)
        self.plan.replans += 1
        if new != n and len(self.plan.history) < 200:
            self.plan.history.append((it, new, round(self.budget_s_left(), 1)))
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

    def _g(self, p: float, window: tuple[float, float]) -> float:
        a, b = window
        return 1.0 + (self.growth - 1.0) * min(max((p - a) / (b - a), 0.0), 1.0)

    def _predict(self, it: int, n: int) -> float:
        """Seconds from now to the end of a run of n iterations (at iteration `it` now)."""
        c = replace(self.cfg, iterations=n)
        window = self._growth_window(c)
        g_now = self._g(it / n, window)
        base = self.c_step / g_now  # cost per unit of g, fitted to the recent cost
        # Training steps: midpoint rule over 64 slices of the remaining run.
        steps, k = n - it, 64
        total = 0.0
        for j in range(k):
            p = (it + (j + 0.5) * steps / k) / n
            total += base * self._g(p, window) * steps / k
        g_late = self._g(1.0, window) / g_now
        total += self._count_routines(c, it, n) * self.t_routine * g_late
        if c.test_every:
            total += self._count(c, c.test_every, it, n - 1) * self.t_eval * g_late
        if c.checkpoint_every:
            total += self._count(c, c.checkpoint_every, it, n - 1) * self.t_ckpt
        total += self.t_eval * g_late + self.t_save  # final evaluation and outputs
        return total

    @staticmethod
    def _count(c: TrainConfig, paper_period: float, lo: int, hi: int) -> int:
        """Multiples of the scaled period in (lo, hi]."""
        if hi <= lo:
            return 0
        period = schedule.at(c, paper_period)
        if period <= 1:
            return hi - lo
        return max(0, math.floor(hi / period + 1e-9) - math.floor(lo / period + 1e-9))

    def _count_routines(self, c: TrainConfig, it: int, n: int) -> int:
        if c.method != "content_aware":
            return 0
        start, end = schedule.routine_window(c)
        full = self._count(c, c.routine_every, max(it, start - 1), min(end, n - 1))
        late = self._count(c, c.late_downscale_every, max(it, end, start), n - 1)
        return full + late

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
        return {"time_budget_s": p.budget_s, "planned_iterations_initial": p.initial_iterations,
                "calibration_step_s": round(p.calib_step_s, 5), "calibration_render_s": round(p.calib_render_s, 5),
                "replans": p.replans, "plan_history": p.history}

    def state_dict(self) -> dict:
        return {"plan": vars(self.plan).copy(), "growth": self.growth, "c_step": self.c_step,
                "t_routine": self.t_routine, "t_eval": self.t_eval, "t_ckpt": self.t_ckpt, "t_save": self.t_save,
                "last_replan": self.last_replan}

    def load_state_dict(self, state: dict) -> None:
        self.plan = Plan(**state["plan"])
        self.growth, self.c_step = state["growth"], state["c_step"]
        self.t_routine, self.t_eval, self.t_ckpt, self.t_save = (state[k] for k in ("t_routine", "t_eval", "t_ckpt",
                                                                                      "t_save"))
        self.last_replan = state["last_replan"]
