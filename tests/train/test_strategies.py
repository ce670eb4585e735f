"""Training strategies and components (ctgs.train.strategies, ctgs.train.components): one strategy per method, the
parts a config turns on, and the order in which the trainer calls their hooks (ctgs.train.hooks)."""

from __future__ import annotations

import pytest

from ctgs.runs import training_scene
from ctgs.scene.demo import make_demo_scene
from ctgs.stages.train import resolve_config
from ctgs.train import components
from ctgs.train.config import METHODS
from ctgs.train.events import Step
from ctgs.train.hooks import Component
from ctgs.train.loop.trainer import Trainer
from ctgs.train.strategies import STRATEGIES, ContentAware, Densify, FixedTexture, make_strategy


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(str(tmp_path_factory.mktemp("scene") / "demo"), num_views=6, width=48, height=36,
                           points=200)


def _trainer(scene, run, sets=()):
    cfg = resolve_config(scene, run, None, 20, ("threads=1", "backend='cpu'", *sets), None, False, None, None,
                         preset="fast")
    return Trainer(cfg, training_scene(cfg), run)


def test_every_method_has_its_strategy_and_texture_mode():
    assert set(STRATEGIES) == set(METHODS)
    modes = {m: make_strategy(m).texture_mode for m in METHODS}
    assert modes == {"content_aware": "content_aware", "2dgs": "none", "fixed_texture": "fixed"}
    assert isinstance(make_strategy("fixed_texture"), Densify) and make_strategy("content_aware").starts_textures


def test_a_run_holds_the_parts_its_config_turns_on_in_calling_order(scene, tmp_path):
    plain = _trainer(scene, str(tmp_path / "plain"), ("exposure_comp=false", "max_params_per_value=0"))
    assert [type(p) for p in plain.parts] == [ContentAware, components.TimeBudget]
    assert plain.exposure is None and plain.part(components.Shell) is None
    every = _trainer(scene, str(tmp_path / "every"), ("method='fixed_texture'", "init_shell=20",
                                                      "virtual_coverage=0.1", "lambda_normal=0.1", "max_params=50000",
                                                      "exposure_comp=true"))
    assert [type(p) for p in every.parts] == [FixedTexture, components.Shell, components.VirtualCoverage,
                                             components.NormalTerm, components.SizeBudget,
                                             components.ExposureCompensation, components.TimeBudget]
    assert every.strategy is every.parts[0] and every.exposure is every.part(components.ExposureCompensation)


def test_the_state_holds_values_never_a_part_nor_the_trainer(scene, tmp_path):
    """TrainState is data: the parts get the time budget's decisions (the calendar's shift, whether textures may start,
    whether a routine date is kept), the shell's sphere and the exposure gains as values, never a part, a part's method
    or the trainer; the only functions it lends are the loop's own log and NaN guard."""
    import dataclasses
    import inspect

    t = _trainer(scene, str(tmp_path / "run"), ("init_shell=20", "exposure_comp=true", "exposure_in_E=true",
                                                "time_budget=0.05"))
    events = list(t.run())
    st = t.state
    assert st.far_sphere is not None and st.view_gains is not None and st.calibration is not None
    assert any(type(ev).__name__ == "Planned" for ev in events)
    for f in dataclasses.fields(st):
        value = getattr(st, f.name)
        owner = getattr(value, "__self__", None)  # a bound method's object
        assert not isinstance(value, (Component, Trainer)) and not isinstance(owner, Component), f.name
        if callable(value) and not isinstance(value, type):
            assert f.name in ("log", "check_finite") and (owner is t or inspect.isfunction(value)), f.name


def _keys_read(strategy: type) -> set[str]:
    """The config keys a strategy's code reads: `cfg.X` in its class, in the functions and classes of its module and of
    ctgs.train.routines that the code it reaches names (followed through imports), and in the
    ctgs.train.config.schedule functions it calls (and those call)."""
    import ast
    import importlib
    import inspect

    trees = {}

    def parse(module):
        if module not in trees:
            trees[module] = ast.parse(inspect.getsource(importlib.import_module(module)))
        return trees[module]

    def reads(node) -> set[str]:
        return {n.attr for n in ast.walk(node) if isinstance(n, ast.Attribute) and (
            isinstance(n.value, ast.Name) and n.value.id == "cfg"
            or isinstance(n.value, ast.Attribute) and n.value.attr == "cfg")}

    sched = {f.name: f for f in parse("ctgs.train.config.schedule").body if isinstance(f, ast.FunctionDef)}

    def sched_keys(name: str, seen: set) -> set[str]:
        if name in seen or name not in sched:
            return set()
        seen.add(name)
        calls = {n.func.id for n in ast.walk(sched[name]) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
        return reads(sched[name]).union(*(sched_keys(c, seen) for c in calls))

    seen, keys = set(), set()

    def visit(module: str, name: str) -> None:
        if (module, name) in seen:
            return
        seen.add((module, name))
        tree = parse(module)
        defs = {n.name: n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
        if name not in defs:
            return
        node = defs[name]
        keys.update(reads(node))
        froms = [n for n in tree.body if isinstance(n, ast.ImportFrom) and n.module
                 and n.module.startswith("ctgs.train.routines")]
        names = {a.asname or a.name: (n.module, a.name) for n in froms for a in n.names}  # from M import f
        modules = {a.asname or a.name: f"{n.module}.{a.name}" for n in froms if n.module == "ctgs.train.routines"
                   for a in n.names}  # from ctgs.train.routines import M (then M.f)
        for n in ast.walk(node):
            if isinstance(n, ast.Name) and n.id != name:
                if n.id in defs:
                    visit(module, n.id)
                elif n.id in names and n.id not in modules:
                    visit(*names[n.id])
            elif isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name):
                if n.value.id in modules:
                    visit(modules[n.value.id], n.attr)
                elif n.value.id == "schedule":
                    keys.update(sched_keys(n.attr, set()))

    visit(strategy.__module__, strategy.__name__)
    return keys


def test_each_strategy_names_exactly_the_config_keys_its_code_reads():
    """A strategy's KEYS (its Settings' fields) are what a reader needs to know of its config: checked against its
    code, so a key added to a routine and not to its strategy's list fails here."""
    import dataclasses

    from ctgs.train.config import TrainConfig, load_config
    from ctgs.train.strategies.base import RUN_KEYS

    for strategy in (ContentAware, Densify):
        assert set(strategy.KEYS) == _keys_read(strategy) - set(RUN_KEYS), strategy.__name__
    assert FixedTexture.KEYS == (*Densify.KEYS, "fixed_texture_res")  # its textures are made at initialisation
    for strategy in (ContentAware, Densify, FixedTexture):
        assert len(set(strategy.KEYS)) == len(strategy.KEYS)
        settings = strategy.settings(load_config(None, preset="fast"))
        assert [f.name for f in dataclasses.fields(settings)] == list(strategy.KEYS)
        defaults = TrainConfig()
        assert all(f.default == getattr(defaults, f.name) for f in dataclasses.fields(strategy.Settings))
        with pytest.raises(dataclasses.FrozenInstanceError):
            settings.max_primitives = 1


class Recorder(Component):
    """A component that records each hook called on it: (hook, the state's iteration then)."""

    def __init__(self):
        self.calls = []

    def __getattribute__(self, name):
        attr = object.__getattribute__(self, name)
        if name in ("calls", "__class__", "__dict__") or not callable(attr) or name.startswith("_"):
            return attr

        def record(*args, **kwargs):
            self.calls.append((name, args[0].it if args else None))
            return attr(*args, **kwargs)
        return record


def test_the_hooks_are_called_in_their_order_within_each_iteration(scene, tmp_path):
    t = _trainer(scene, str(tmp_path / "run"), ("checkpoint_every=1500", "log_every=1"))  # a checkpoint every iteration
    t.time.estimator = None  # (its calibration times the hooks of training steps on a copy)
    rec = Recorder()
    t.parts.append(rec)
    for ev in t.run():
        if isinstance(ev, Step) and ev.it == 2:
            break
    step = ["render", "train_render", "post_backward", "post_step", "step_end", "timed_step", "log_fields"]
    # iteration 1: its checkpoint (written with each part's state), timed; then after_step
    assert rec.calls == [("begin", 0), *[(h, 1) for h in step], ("checkpoint", 1), ("timed", 1),
                         ("after_step", 1), *[(h, 2) for h in step]]


@pytest.mark.parametrize("final", [1.0 / 255.0, 0.0])
def test_the_final_prune_removes_what_cannot_reach_alpha_1_255_before_the_model_is_scored(scene, tmp_path, final):
    """prune_opacity_final (the `paper` preset: 1/255, as the authors' save) prunes after the last iteration, before
    the final evaluation and model.pt; 0 (the CPU presets) keeps every primitive."""
    import json
    import os

    import torch

    from ctgs.runs import load_run
    from ctgs.train.loop.progress import run_with_progress

    run = str(tmp_path / "run")
    # (the routines' own prunes off: only the final one may remove the faint primitives)
    trainer = _trainer(scene, run, ("texture_trim=0", "prune_opacity=0", "prune_opacity_late=0",
                                    f"prune_opacity_final={final}"))
    with torch.no_grad():  # a tenth of the primitives made too faint to be drawn (the run's 20 steps lift few of them)
        trainer.model.opacity_logits[::10] = -12.0
    run_with_progress(trainer, quiet=True)
    log = [json.loads(line) for line in open(os.path.join(run, "log.jsonl"))]
    prunes = [r for r in log if r["type"] == "routine" and r["kind"] == "final_prune"]
    model = load_run(run).model
    if final > 0:
        assert len(prunes) == 1 and prunes[0]["pruned"] > 0
        assert float(model.opacities.min()) >= final
        assert [r["type"] for r in log[log.index(prunes[0]):]][-1] == "test"
    else:
        assert not prunes and float(model.opacities.min()) < 1.0 / 255.0


@pytest.mark.parametrize("from_start", [True, False])
def test_the_textures_adam_steps_count_from_the_first_iteration_with_the_authors_rule(scene, tmp_path, from_start):
    """torch's Adam in the authors' code counts the textures' steps while their learning rate is 0: at the texture
    start their step count is the iteration's, not 0 (so no bias correction on their first steps)."""
    from ctgs.train.step.adam import TEX_PARAM

    trainer = _trainer(scene, str(tmp_path / "run"), ("texture_start=2000", f"texture_steps_from_start={from_start}"))
    st = trainer.state
    st.it = 7
    trainer.strategy.start_textures(st)
    assert st.opt.steps[TEX_PARAM] == (7 if from_start else 0)
