"""ctgs.runs, the one package for run folders: its public names, a finished run written (the summary, then model.pt,
which marks it finished) and read back, and the scene a training loads and the one a finished run was trained on."""

from __future__ import annotations

import os
import subprocess
import sys
from types import SimpleNamespace

import pytest
import torch

import ctgs.runs as runs
from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.model.surfels import SurfelModel
from ctgs.scene import load_scene
from ctgs.scene.demo import make_demo_scene

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_every_public_name_resolves():
    for name in runs.__all__:
        assert getattr(runs, name) is not None, name
    with pytest.raises(AttributeError):
        runs.no_such_name  # noqa: B018


def _model_state() -> dict:
    """A model of 3 untextured surfels at SH degree 0, as a state dict."""
    n = 3
    model = SurfelModel(means=torch.rand(n, 3), log_scales=torch.zeros(n, 2), quats=torch.tensor([[1.0, 0, 0, 0]] * n),
                        opacity_logits=torch.zeros(n), sh=torch.rand(n, 1, 3), textures_raw=torch.zeros(0, 3),
                        k_min=torch.ones(n), t2p_exp=torch.zeros(n, dtype=torch.int32),
                        tex_res=torch.zeros(n, 2, dtype=torch.int32), tex_offset=torch.zeros(n, dtype=torch.int64))
    model.validate()
    return model.state_dict()


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return make_demo_scene(str(tmp_path_factory.mktemp("scene") / "demo"), num_views=9, width=32, height=24,
                           points=100, supersample=1)


def test_a_finished_run_is_written_and_read_back(tmp_path):
    run_dir = str(tmp_path / "run")
    runs.write_config(run_dir, {"seed": 0})
    model_id = runs.new_model_id()
    state = _model_state()
    runs.write_finished(run_dir, {"iterations": 7, "model_id": model_id},
                        {"model": state, "scene_dir": "/nowhere", "images": "images_2", "holdout": 4,
                         "iteration": 7, "config": {"seed": 0}, "world_origin": [0.0, 0.0, 0.0], "model_id": model_id})
    assert sorted(os.listdir(run_dir)) == sorted([runs.CONFIG_FILE, runs.MODEL_FILE, runs.SUMMARY_FILE])
    run = runs.load_run(run_dir)
    assert (run.images, run.holdout, run.iteration, run.summary["model_id"]) == ("images_2", 4, 7, model_id)
    back = run.model.state_dict()
    for k, v in state.items():
        assert torch.equal(back[k], v) if torch.is_tensor(v) else back[k] == v, k
    with pytest.raises(UserError, match="not on this machine"):
        runs.with_scene(run)


def test_a_model_that_cannot_be_written_leaves_no_summary(tmp_path, monkeypatch):
    run_dir = str(tmp_path / "run")
    os.makedirs(run_dir)

    def full(*_a, **_k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic, "torch_save", full)
    with pytest.raises(OSError):
        runs.write_finished(run_dir, {"model_id": "x"}, {"model_id": "x"})
    assert os.listdir(run_dir) == []


def test_the_training_scene_and_the_finished_runs_scene(scene_dir):
    cfg = SimpleNamespace(scene_dir=scene_dir, images="images", holdout=4, background=[0.0, 0.0, 0.0],
                          validation_holdout=0)
    scene = runs.training_scene(cfg)
    whole = load_scene(scene_dir, holdout=4)
    assert [v.name for v in scene.test] == [v.name for v in whole.test] == ["000.png", "004.png", "008.png"]
    tuned = runs.training_scene(SimpleNamespace(**{**vars(cfg), "validation_holdout": 3}))
    assert not {v.name for v in tuned.train + tuned.test} & {v.name for v in whole.test}  # test views never seen
    run = SimpleNamespace(scene_dir=scene_dir, images="images", holdout=4)
    assert [v.name for v in runs.run_scene(run, load_images=False).test] == [v.name for v in whole.test]


def test_the_checkpoint_probe_runs_as_a_module(tmp_path):
    done = subprocess.run([sys.executable, "-m", "ctgs.runs.checkpoint", str(tmp_path)], capture_output=True,
                          text=True, cwd=ROOT, timeout=120)
    assert (done.returncode, done.stdout, done.stderr) == (0, "", "")
