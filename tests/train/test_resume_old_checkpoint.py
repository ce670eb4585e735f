"""A checkpoint written by an earlier trainer (tests/data/resume_736cf4e: commit 736cf4e, before the training
strategies and components) still resumes, and on a machine that computes its first 30 iterations as the writer's did,
the resumed run is bit-identical to an uninterrupted one of this code.

Each folder holds iteration 30 of a 60-iteration run (the SETS below, preset fast, the demo scene of the fixture):
checkpoints/last.pt and log.jsonl up to it; config.toml is written here, as the run wrote it."""

from __future__ import annotations

import os
import shutil

import pytest
import torch

from ctgs.runs import load_run, write_config
from ctgs.runs.checkpoint import read_checkpoint
from ctgs.scene.demo import make_demo_scene
from ctgs.stages.train import resolve_config, train_main
from train_helpers import run_log

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
FIXTURES = os.path.join(ROOT, "tests", "data", "resume_736cf4e")
CHECKPOINT_AT = 30
SETS = ("iterations=60", "schedule_scale=0.04", "checkpoint_every=750", "backend='cpu'", "max_init_points=200",
        "threads=1", "routine_margin=0", "tau_tr_start=2.0", "tau_tr_end=2.0", "min_t2p_exp=0", "start_texels=4.0",
        "log_every=1", "error_from_steps=false")
# error_from_steps: as the checkpoints' writer computed E (rendered at the routine; it kept no step errors to resume).
# content_aware: texture start at 20, a full routine at 40 after the checkpoint. 2dgs: densification at 20, 40, 60,
# so the checkpoint holds 10 steps of gradient statistics; opacity reset at 40.
METHODS = {"content_aware": (), "2dgs": ("method='2dgs'", "densify_every=500", "densify_from=0",
                                         "opacity_reset_every=1000")}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(str(tmp_path_factory.mktemp("scene") / "demo"), num_views=10, width=48, height=36,
                           points=300)


def _same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        torch.equal(a[k], b[k]) if isinstance(a[k], torch.Tensor) else a[k] == b[k] for k in a)


@pytest.mark.parametrize("method", list(METHODS))
def test_a_checkpoint_of_the_earlier_trainer_resumes(scene, tmp_path, method):
    sets = SETS + METHODS[method]
    reference = str(tmp_path / "whole")
    train_main(scene, reference, preset="fast", sets=sets, quiet=True)
    run = str(tmp_path / "resumed")
    shutil.copytree(os.path.join(FIXTURES, method), run)
    write_config(run, resolve_config(scene, run, None, None, sets, None, False, None, None, preset="fast").to_dict())
    old = read_checkpoint(os.path.join(run, "checkpoints", "last.pt"))  # numpy's random state as an array
    assert old["iteration"] == CHECKPOINT_AT and "acc" in old and "textures_started" in old

    train_main(scene, run, resume=True, quiet=True)
    resumed, whole = load_run(run), load_run(reference)
    assert resumed.iteration == whole.iteration == 60
    log, ref = run_log(run), run_log(reference)
    assert [r["it"] for r in log if r["type"] == "step"] == list(range(1, 61))
    # The whole run's checkpoint at iteration 30 (kept as prev.pt after the final one): where this machine computes
    # the first 30 iterations as the writer's did, everything after must be bit-identical too.
    mine = torch.load(os.path.join(reference, "checkpoints", "prev.pt"), map_location="cpu", weights_only=True)
    assert mine["iteration"] == CHECKPOINT_AT
    if _same_state(old["model"], mine["model"]):
        # the strategy's state is kept under the keys it had (content-aware: textures_started; 2dgs: the gradient
        # statistics since the last densification, "acc")
        key = "acc" if method == "2dgs" else "textures_started"
        assert key in mine and (_same_state(old[key], mine[key]) if method == "2dgs" else old[key] == mine[key])
        assert _same_state(resumed.model.state_dict(), whole.model.state_dict())
        assert log == ref
    else:  # another CPU's arithmetic: the resumed run is the same training, to rounding
        psnr = [[r["psnr"] for r in rows if r["type"] == "test"][-1] for rows in (log, ref)]
        assert abs(psnr[0] - psnr[1]) < 0.5, psnr
