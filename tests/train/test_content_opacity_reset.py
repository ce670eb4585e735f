"""content_opacity_reset: a content-aware run clamps opacities after the full routine its calendar names, and the
next full routine prunes what the training views did not bring back
(ctgs.train.config.schedule.content_opacity_reset)."""

from __future__ import annotations

import json
import os

import pytest

from ctgs.runs import training_scene, write_config
from ctgs.scene.demo import make_demo_scene
from ctgs.stages.train import resolve_config
from ctgs.train.events import Routine
from ctgs.train.loop.trainer import Trainer

# 100 iterations at paper scale x 0.04: textures from 20, full routines every 40 (40 and 80; routine_margin=0),
# opacity resets due every 1000 x 0.04 = 40 up to densify_until 1500 x 0.04 = 60: one after the routine at 40.
SETS = ("iterations=100", "schedule_scale=0.04", "backend='cpu'", "max_init_points=200", "threads=1",
        "routine_margin=0", "opacity_reset_every=1000", "densify_until=1500", "test_every=0", "checkpoint_every=0",
        "log_every=1", "exposure_comp=false")  # (the reset's mechanics, without the preset's learned exposures)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(str(tmp_path_factory.mktemp("scene") / "demo"), num_views=8, width=48, height=36, points=200)


def _run(scene, run, extra):
    cfg = resolve_config(scene, run, None, None, SETS + extra, None, False, None, None, preset="fast")
    trainer = Trainer(cfg, training_scene(cfg), run)
    write_config(run, cfg.to_dict())
    seen = []
    for ev in trainer.run():
        if isinstance(ev, Routine) and ev.kind in ("full", "opacity_reset"):
            # (the trainer hands over an iteration's routines after all of them ran: the model is the reset one)
            seen.append((ev.it, ev.kind, float(trainer.model.opacities.detach().max()), trainer.model.num_primitives,
                         dict(ev.stats)))
    return cfg, seen


def test_reset_after_the_routine_then_pruned_by_the_next(scene, tmp_path):
    cfg, seen = _run(scene, str(tmp_path / "on"), ("content_opacity_reset=true",))
    assert [(it, kind) for it, kind, *_ in seen] == [(40, "full"), (40, "opacity_reset"), (80, "full")]
    value = 2 * cfg.prune_opacity
    assert seen[1][2] <= value * (1 + 1e-5) and seen[1][3] == seen[0][3]  # clamped, nobody removed by the reset
    log = [json.loads(line) for line in open(os.path.join(str(tmp_path / "on"), "log.jsonl"))]
    reset = [r for r in log if r["type"] == "routine" and r["kind"] == "opacity_reset"]
    assert len(reset) == 1 and reset[0]["it"] == 40 and reset[0]["value"] == pytest.approx(value)
    # The same run without the reset (the default, the paper): the same first routine, no reset, and the routine at
    # 80 prunes fewer: the reset's surfels that did not come back above prune_opacity in the 40 steps between.
    _, off = _run(scene, str(tmp_path / "off"), ())
    assert [(it, kind) for it, kind, *_ in off] == [(40, "full"), (80, "full")]
    assert off[0][4] == seen[0][4] and off[0][2] > 2 * value  # the same routine; without the reset, opaque surfels
    assert seen[2][4]["pruned"] > off[1][4]["pruned"], (seen, off)


def test_prune_opacity_zero_resets_to_3dgs_value_and_stays_finite(scene, tmp_path):
    # The extreme: prune_opacity = 0 would make the reset value 0 (logit -inf); it is 0.01 instead, and the run ends.
    _, seen = _run(scene, str(tmp_path / "zero"), ("content_opacity_reset=true", "prune_opacity=0.0"))
    reset = [s for s in seen if s[1] == "opacity_reset"]
    assert len(reset) == 1 and reset[0][4]["value"] == 0.01 and reset[0][2] <= 0.01 * (1 + 1e-5)


def test_full_routines_run_lean(scene, tmp_path, monkeypatch):
    """The trainer's full routines run in the lean order (the paper's order, lean=False, ends in the same state with
    more texels in between: tests/train/test_routines_image.py)."""
    from ctgs.train.strategies import content_aware

    calls = []
    real = content_aware.full_routine
    monkeypatch.setattr(content_aware, "full_routine", lambda *a, **k: (calls.append(k.get("lean", True)),
                                                                        real(*a, **k))[1])
    _run(scene, str(tmp_path / "run"), ())
    assert calls == [True, True]


def test_periodic_tests_score_the_model_before_the_routines_and_the_reset(scene, tmp_path):
    """Test evaluations fall on the same multiples as the routines and opacity resets: each scores the model after the
    step before the multiple, never one just reset (a run of bonsai logged ~14 dB there, 28 dB a period later)."""
    run = str(tmp_path / "tests")
    sets = tuple(s for s in SETS if not s.startswith("test_every")) + ("test_every=1000", "content_opacity_reset=true")
    cfg = resolve_config(scene, run, None, None, sets, None, False, None, None, preset="fast")
    trainer = Trainer(cfg, training_scene(cfg), run)
    write_config(run, cfg.to_dict())
    for _ in trainer.run():
        pass
    log = [json.loads(line) for line in open(os.path.join(run, "log.jsonl"))]
    tests = [r["it"] for r in log if r["type"] == "test"]
    routines = {r["it"] for r in log if r["type"] == "routine"}
    assert tests == [39, 79, 100], tests
    assert {40, 80} <= routines and not routines & set(tests[:-1])
