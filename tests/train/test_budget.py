"""The time-budget planner on a simulated clock: a run whose per-iteration cost grows (like a content-aware
run) ends within 10% of its budget, re-planning as it goes, whatever the prior growth guess."""

from __future__ import annotations

import pytest

from ctgs.train import budget as budget_mod
from ctgs.train import schedule
from ctgs.train.budget import BudgetPlanner
from ctgs.train.config import load_config


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def simulate(monkeypatch, cfg, budget_s, step0, growth, routine_s, prior_growth=None, noise=0.0, plans=None):
    """Drive the planner like the trainer does; the true cost of a step is step0 * (1 + (growth - 1) * p)
    over the routine window (p = its progress), times a factor exp(N(0, noise)) drawn every 10 steps (a shared
    machine's load). Appends (iteration, new plan) to `plans` if given. Returns (wall seconds, iterations,
    initial plan)."""
    import math
    import random

    rng = random.Random(0)
    factor = 1.0
    clock = Clock()
    monkeypatch.setattr(budget_mod.time, "monotonic", clock)
    planner = BudgetPlanner(cfg, budget_s, 0.0, n_train=20, n_test=3)
    if prior_growth is not None:
        planner.growth = prior_growth
    clock.t += 1.0  # loading the scene
    clock.t += 3 * (step0 + step0 / 3)  # calibration
    cfg.iterations = planner.calibrate(step0, step0 / 3)
    initial = cfg.iterations
    it = 0
    while it < cfg.iterations:
        it += 1
        if noise and it % 10 == 0:
            factor = math.exp(rng.gauss(0.0, noise))
        start, end = schedule.routine_window(cfg)
        p = min(max((it - start) / max(end - start, 1), 0.0), 1.0)
        step = step0 * (1 + (growth - 1) * p) * factor
        clock.t += step
        planner.observe_step(step)
        if schedule.routine_kind(cfg, it) in ("full", "late"):
            clock.t += routine_s * (1 + (growth - 1) * p)
            planner.observe_routine(routine_s * (1 + (growth - 1) * p))
        if cfg.test_every and schedule.every(cfg, cfg.test_every, it) and it < cfg.iterations:
            clock.t += 3 * step0 / 3
        new = planner.maybe_replan(it)
        if new is not None:
            cfg.iterations = new
            if plans is not None:
                plans.append((it, new))
    clock.t += 3 * step0 / 3 * growth + 0.2  # final evaluation and save
    return clock.t, it, initial


@pytest.mark.parametrize("true_growth,prior", [(2.5, None), (5.0, None), (1.2, None), (3.0, 1.0)])
def test_budget_run_ends_within_ten_percent(monkeypatch, true_growth, prior):
    cfg = load_config(None, preset="fast")
    budget_s = 600.0
    wall, iterations, initial = simulate(monkeypatch, cfg, budget_s, step0=0.05, growth=true_growth,
                                         routine_s=1.0, prior_growth=prior)
    assert abs(wall - budget_s) <= 0.10 * budget_s, (wall, iterations, initial)
    assert wall <= budget_s * 1.02
    assert iterations > 1000


def test_a_budget_too_small_for_any_training_stops_at_once(monkeypatch):
    cfg = load_config(None, preset="fast")
    wall, iterations, _ = simulate(monkeypatch, cfg, 2.0, step0=0.5, growth=2.0, routine_s=5.0)
    assert iterations <= 2


def test_noisy_step_times_do_not_swing_the_plan(monkeypatch):
    # Every schedule is a fraction of the planned run: a plan that follows each burst of load moves every
    # event back and forth. Step times noisy by ~30% per 10 steps: after the first 10% of the run no re-plan
    # may change the plan by more than 25%, and the run still ends within its budget.
    import math

    cfg = load_config(None, preset="fast")
    plans: list = []
    budget_s = 900.0
    wall, iterations, _ = simulate(monkeypatch, cfg, budget_s, step0=0.05, growth=2.5, routine_s=1.0, noise=0.3,
                                   plans=plans)
    changes = [abs(math.log(b / a)) for (ia, a), (_, b) in zip(plans, plans[1:]) if ia > 0.1 * iterations]
    assert changes and max(changes) < math.log(1.25), max(changes)
    assert abs(wall - budget_s) <= 0.10 * budget_s and wall <= budget_s * 1.02


def test_short_plan_warning_names_the_budget_and_the_fixes():
    from ctgs.train.budget import SHORTEST_MEASURED, short_plan_warning

    assert short_plan_warning(SHORTEST_MEASURED, 60.0, 0.05, 98304) is None
    line = short_plan_warning(85, 120.0, 1.3, 393216)
    assert "2.0 min buys about 85 iterations" in line and "1.30 s per step at 393k pixels" in line
    assert "--images" in line and "more minutes" in line and "\n" not in line
    assert "3 s buys about 1 iteration here" in short_plan_warning(1, 3.0, 0.03, 49152)


@pytest.mark.parametrize("quiet", [True, False])
def test_a_budget_that_buys_a_short_run_warns_once_on_stderr(tmp_path, capsys, quiet):
    """End to end, with and without the progress display: a budget far too small for the scene still trains (the
    user asked for it) and says so."""
    from ctgs.scene.demo import make_demo_scene
    from ctgs.stages.train import train_main

    scene_dir = make_demo_scene(str(tmp_path / "demo"), num_views=5, width=48, height=36, points=150)
    summary = train_main(scene_dir, str(tmp_path / "run"), preset="fast", time_budget=0.01, quiet=quiet,
                         sets=("threads=1",))
    err = capsys.readouterr().err
    assert err.count("ctgs train: warning:") == 1 and "shortest run measured" in err
    assert summary["iterations"] < 1000 and summary["planned_iterations_initial"] < 1000
