"""error_from_steps: E from the training steps' own backward (ctgs.train.routines.error.StepErrors) instead of renders
at the routine. On a model that does not change, the steps' E is the rendered E of the same views with the loss's error image;
a run with it renders nothing in its routines, resumes exactly, and a CUDA-less fallback renders E as before."""

from __future__ import annotations

import json

import pytest
import torch

from ctgs.render import BackwardStats, render
from ctgs.train.config import TrainConfig
from ctgs.train.routines.error import StepErrors, accumulate_error
from ctgs.train.step.loss import training_loss

from train_helpers import camera, model


def _views(n: int = 4):
    """Cameras shifted along z, each with a random target image."""
    g = torch.Generator().manual_seed(5)
    cams = [camera(z_shift=0.1 * k) for k in range(n)]
    return [(c, torch.rand(c.height, c.width, 3, generator=g)) for c in cams]


def test_step_errors_of_a_fixed_model_are_the_rendered_E_of_its_views():
    m = model([[0.0, 0.0, 3.0], [0.3, 0.1, 3.5], [-0.4, -0.2, 4.0], [0.1, 0.3, 2.5]],
              [[0.3, 0.2], [0.4, 0.3], [0.5, 0.4], [0.2, 0.2]], [0.7, 0.6, 0.8, 0.5], [[4, 4], [6, 4], [2, 2], [4, 6]])
    cfg = TrainConfig()
    acc, reference = StepErrors(), []
    for cam, gt in _views():
        sink = BackwardStats()
        out = render(m.render_inputs(), cam, backend="cpu", sh_degree=0, backward_stats=sink)
        terms = training_loss(out.rgb, gt, m, cam, cfg, rasterized=out.rasterized, want_error=True)
        sink.error_image = terms.error_image
        terms.total.backward()
        acc.add(sink.contrib, sink.err, cam.width * cam.height)
        with torch.no_grad():  # the forward's statistics of the same error image
            stats = render(m.render_inputs(), cam, backend="cpu", sh_degree=0, error_image=terms.error_image).stats
        reference.append((stats.err, stats.contrib, cam.width * cam.height))
    assert acc.covers(m.num_primitives) and acc.steps == 4
    E_ref = accumulate_error(reference)
    assert E_ref.gt(0).sum() >= 3
    torch.testing.assert_close(acc.E(), E_ref, atol=1e-9, rtol=1e-4)
    assert not acc.covers(m.num_primitives + 1)  # a changed model is not covered


# The schedule of tests/train/test_resume_and_guard.py (texture start at 20, a checkpoint at 30, full routines at 40
# and 80 that split and upscale), with E from the steps.
SETS = ("iterations=100", "schedule_scale=0.04", "checkpoint_every=750", "backend='cpu'", "max_init_points=200",
        "threads=1", "routine_margin=0", "tau_tr_start=2.0", "tau_tr_end=2.0", "min_t2p_exp=0", "start_texels=4.0",
        "log_every=1", "error_from_steps=true")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from ctgs.scene.demo import make_demo_scene

    return make_demo_scene(str(tmp_path_factory.mktemp("scene") / "demo"), num_views=8, width=48, height=36,
                           points=300)


def test_a_run_with_step_errors_renders_no_view_in_its_routines(scene, tmp_path, monkeypatch):
    from ctgs.stages.train import train_main
    import ctgs.train.routines.passes as routines_mod

    calls = []
    real = routines_mod.compute_E
    monkeypatch.setattr(routines_mod, "compute_E", lambda *a, **k: calls.append(1) or real(*a, **k))
    run = tmp_path / "run"
    train_main(scene, str(run), preset="fast", sets=SETS, quiet=True)
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    full = [r for r in log if r["type"] == "routine" and r["kind"] == "full"]
    assert len(full) >= 2 and all(r["E_steps"] > 0 for r in full), full
    assert full[0]["split"] + full[0]["upscaled"] > 0  # E drove decisions
    assert not calls  # E came from the steps every time
    assert json.loads((run / "train_summary.json").read_text())["seconds_in"]["routine"] > 0


def test_a_resumed_run_with_step_errors_ends_at_the_same_model(scene, tmp_path):
    """The statistics since the last routine are in the checkpoint: stopped after the checkpoint at 30 and before the
    routine at 40 (whose E covers the steps since the start), the resumed run ends at the uninterrupted run's model."""
    from ctgs.runs import training_scene
    from ctgs.runs import write_config
    from ctgs.runs import load_run
    from ctgs.stages.train import resolve_config, train_main
    from ctgs.train.events import Step
    from ctgs.train.loop.trainer import Trainer

    whole = str(tmp_path / "whole")
    train_main(scene, whole, preset="fast", sets=SETS, quiet=True)
    run = str(tmp_path / "interrupted")
    cfg = resolve_config(scene, run, None, None, SETS, None, False, None, None, preset="fast")
    trainer = Trainer(cfg, training_scene(cfg), run)
    write_config(run, cfg.to_dict())
    gen = trainer.run()
    for ev in gen:  # stop without any cleanup (as a kill would)
        if isinstance(ev, Step) and ev.it == 36:
            break
    gen.close()
    assert torch.load(f"{run}/checkpoints/last.pt", weights_only=True)["step_errors"]["steps"] == 30
    train_main(scene, run, resume=True, quiet=True)
    a, b = load_run(run).model.state_dict(), load_run(whole).model.state_dict()
    for k, v in a.items():
        if isinstance(v, torch.Tensor):
            assert torch.equal(v, b[k]), k
