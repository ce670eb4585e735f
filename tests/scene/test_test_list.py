"""A scene's own list of test views (test_views.txt): read by the loader, recorded by training, checked by eval."""

from __future__ import annotations

import json
import os
from types import SimpleNamespace

import pytest
import torch
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.runs.scene import run_scene
from ctgs.scene import load_scene


def _write(scene_dir, text: str) -> None:
    with open(os.path.join(scene_dir, "test_views.txt"), "w") as f:
        f.write(text)


def test_list_names_the_test_views(tiny_demo):
    # a protocol's list over all the photos may name photos SfM did not register: left out, counted
    _write(tiny_demo, "# the protocol's test views\n003.png\n\n007.png  # a comment\nDSC_not_registered.jpg\n")
    scene = load_scene(tiny_demo, load_images=False)
    assert [v.name for v in scene.test] == ["003.png", "007.png"]
    assert [v.name for v in scene.train] == [f"{i:03d}.png" for i in range(10) if i not in (3, 7)]
    assert scene.meta["test_names"] == ["003.png", "007.png"] and scene.meta["test_list"] == "test_views.txt"
    assert scene.meta["split"].startswith("2 test views from test_views.txt, 8 training views (1 listed")


def test_list_matches_a_changed_extension_and_holdout_zero_keeps_every_view(tiny_demo):
    _write(tiny_demo, "001.jpg\n")  # a downsampled folder may store another extension than the model names
    assert [v.name for v in load_scene(tiny_demo, load_images=False).test] == ["001.png"]
    everything = load_scene(tiny_demo, holdout=0, load_images=False)
    assert everything.test == [] and len(everything.train) == 10 and "test_names" not in everything.meta


def test_without_a_list_every_8th_view_is_a_test_view(tiny_demo):
    scene = load_scene(tiny_demo, load_images=False)
    assert [v.name for v in scene.test] == ["000.png", "008.png"] and "split" not in scene.meta


@pytest.mark.parametrize("text, words", [
    ("", "lists no image"),
    ("# only a comment\n", "lists no image"),
    ("a.png\nb.png\n", "none of its 2 names"),
    ("001.png\n001.png\n", "more than once"),
])
def test_a_bad_list_is_one_clear_error(tiny_demo, text, words):
    _write(tiny_demo, text)
    with pytest.raises(UserError, match=words) as err:
        load_scene(tiny_demo, load_images=False)
    assert "test_views.txt" in str(err.value)


def _run(scene_dir, test_views):
    return SimpleNamespace(run_dir="/runs/r", scene_dir=scene_dir, images="images", holdout=8, test_views=test_views)


def test_eval_refuses_a_scene_whose_test_views_changed_since_training(tiny_demo):
    run = _run(tiny_demo, None)  # trained on every 8th view
    assert [v.name for v in run_scene(run, load_images=False).test] == ["000.png", "008.png"]
    _write(tiny_demo, "003.png\n")  # added afterwards: 003 was a training view of that run
    with pytest.raises(UserError, match="every 8th view .* now the 1 its test_views.txt lists"):
        run_scene(run, load_images=False)
    assert [v.name for v in run_scene(_run(tiny_demo, ["003.png"]), load_images=False).test] == ["003.png"]
    _write(tiny_demo, "004.png\n")  # changed
    with pytest.raises(UserError, match="the 1 views its test_views.txt listed"):
        run_scene(_run(tiny_demo, ["003.png"]), load_images=False)


@pytest.mark.slow
def test_train_and_eval_use_the_list(tiny_demo, tmp_path):
    _write(tiny_demo, "002.png\n005.png\n009.png\n")
    run = str(tmp_path / "run")

    def ctgs(*args):  # in this process: what the stages say, without a new interpreter's start-up
        r = CliRunner().invoke(main, [str(a) for a in args])
        assert r.exit_code == 0, r.stderr
        return r.stderr

    said = ctgs("train", tiny_demo, "-o", run, "--preset", "preview", "--iterations", "20", "--set", "threads=1",
                "--backend", "cpu", "-q")
    assert "views: 3 test views from test_views.txt, 7 training views" in said
    ckpt = torch.load(os.path.join(run, "model.pt"), weights_only=True)
    assert ckpt["test_views"] == ["002.png", "005.png", "009.png"]
    ctgs("eval", run, "--no-lpips")
    metrics = json.load(open(os.path.join(run, "eval", "metrics.json")))
    assert metrics["num_test_views"] == 3 and metrics["test_list"] == "test_views.txt"
    assert sorted(r["name"] for r in metrics["per_image"]) == ["002.png", "005.png", "009.png"]
