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


def simulate(monkeypatch, cfg, budget_s, step0, growth, routine_s, prior_growth=None):
    """Drive the planner like the trainer does; the true cost of a step is step0 * (1 + (growth - 1) * p)
    over the routine window (p = its progress). Returns (wall seconds, iterations, initial plan)."""
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
        start, end = schedule.routine_window(cfg)
        p = min(max((it - start) / max(end - start, 1), 0.0), 1.0)
        step = step0 * (1 + (growth - 1) * p)
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
