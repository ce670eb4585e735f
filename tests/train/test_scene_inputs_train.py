"""Training from the other scene layouts and inputs: the demo scene written as nerfstudio, instant-ngp and Blender
synthetic trains the model its COLMAP scene trains; masked pixels leave no trace in the model or the scores; a Blender
scene without points starts from random points over white; a transparent photo over a random colour."""

from __future__ import annotations

import os
import shutil
import sys

import numpy as np
import pytest
import torch

from ctgs.evaluation.evaluate import EvalOptions, evaluate
from ctgs.io.images import read_image, write_image
from ctgs.runs import load_run
from ctgs.scene.demo import make_demo_scene
from ctgs.stages.train import train_main
from ctgs.train.step.loss import recomposited

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scene"))
from scene_layouts import write_blender, write_instant_ngp, write_nerfstudio  # noqa: E402

ITERATIONS = 40
SETS = ("threads=1", "backend='cpu'")
TEST_NAMES = {"000.png", "008.png"}


def _train(scene: str, run: str, **kw) -> dict:
    return train_main(scene, run, preset="fast", iterations=ITERATIONS, sets=SETS, quiet=True, **kw)


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> str:
    return make_demo_scene(str(tmp_path_factory.mktemp("inputs") / "demo"), num_views=10, width=64, height=48, seed=3,
                           points=600, supersample=2)


@pytest.mark.slow
def test_every_layout_trains_the_colmap_model(demo, tmp_path):
    ns = write_nerfstudio(demo, str(tmp_path / "ns"))
    scenes = {"colmap": demo, "nerfstudio": ns, "instant-ngp": write_instant_ngp(ns, str(tmp_path / "ngp")),
              "blender": write_blender(ns, str(tmp_path / "blender"), TEST_NAMES)}
    # the Blender layout would render over white (as those scenes are evaluated): black here, as the others
    summaries = {k: _train(s, str(tmp_path / f"run_{k}"), background="black") for k, s in scenes.items()}
    ref = summaries["colmap"]
    models = {k: load_run(str(tmp_path / f"run_{k}")).model for k in scenes}
    for k, s in summaries.items():
        assert (s["num_primitives"], s["num_texels"]) == (ref["num_primitives"], ref["num_texels"]), k
        assert s["final_test_psnr"] == pytest.approx(ref["final_test_psnr"], abs=0.01), k
        torch.testing.assert_close(models[k].means, models["colmap"].means, atol=1e-3, rtol=0)


def _masked_copy(demo: str, out: str, noise_seed: int | None) -> str:
    """The demo with a mask over the middle columns of every view; noise_seed: those pixels replaced by noise."""
    shutil.copytree(demo, out)
    mask = np.ones((48, 64))
    mask[:, 24:40] = 0.0
    rng = np.random.default_rng(noise_seed)
    for name in sorted(os.listdir(os.path.join(out, "images"))):
        write_image(os.path.join(out, "masks", name), mask)
        if noise_seed is not None:
            path = os.path.join(out, "images", name)
            pixels = read_image(path)
            pixels[:, 24:40] = rng.random((48, 16, 3))
            write_image(path, pixels)
    return out


@pytest.mark.slow
def test_masked_pixels_leave_no_trace(demo, tmp_path):
    clean, noisy = _masked_copy(demo, str(tmp_path / "clean"), None), _masked_copy(demo, str(tmp_path / "noisy"), 5)
    _train(clean, str(tmp_path / "a"))
    _train(noisy, str(tmp_path / "b"))
    a, b = load_run(str(tmp_path / "a")).model.state_dict(), load_run(str(tmp_path / "b")).model.state_dict()
    for key, value in a.items():
        if torch.is_tensor(value):
            assert torch.equal(value, b[key]), key  # the masked photos' values changed nothing
    scores = [evaluate(str(tmp_path / "a"), EvalOptions(str(tmp_path / f"eval_{k}"), scene_dir=s, lpips=False))
              for k, s in (("clean", clean), ("noisy", noisy))]
    assert scores[0]["psnr"] == pytest.approx(scores[1]["psnr"], abs=1e-9)
    assert scores[0]["ssim"] == pytest.approx(scores[1]["ssim"], abs=1e-9)
    shutil.rmtree(os.path.join(noisy, "masks"))  # without its masks the noise counts
    unmasked = evaluate(str(tmp_path / "a"), EvalOptions(str(tmp_path / "eval_unmasked"), scene_dir=noisy, lpips=False))
    assert unmasked["psnr"] < scores[0]["psnr"] - 1.0


@pytest.mark.slow
def test_blender_scene_without_points_starts_from_random_points_over_white(demo, tmp_path, capfd):
    ns = write_nerfstudio(demo, str(tmp_path / "ns"))
    alpha = np.ones((48, 64))
    alpha[:8] = 0.0  # a transparent band on top of every photo
    scene = write_blender(ns, str(tmp_path / "blender"), TEST_NAMES, points=False,
                          alpha={f"{i:03d}.png": alpha for i in range(10)})
    summary = _train(scene, str(tmp_path / "run"))
    err = capfd.readouterr().err
    assert "random points in the cube the cameras look at" in err and "Blender synthetic scene" in err
    assert "the file's own: 8 training, 2 test views" in err
    assert load_run(str(tmp_path / "run")).config["background"] == [1.0, 1.0, 1.0]
    assert summary["num_primitives"] > 0 and np.isfinite(summary["final_test_psnr"])
    m = evaluate(str(tmp_path / "run"), EvalOptions(str(tmp_path / "eval"), lpips=False))
    render = read_image(os.path.join(tmp_path, "eval", "renders", "test_000.png"))
    assert m["num_views"] == 2 and render[:8].mean() > 0.5  # rendered over white where nothing was learnt


def test_transparent_photo_over_another_colour():
    rgb, alpha = torch.rand(4, 5, 3), torch.rand(4, 5, 1)
    black, white, red = torch.zeros(3), torch.ones(3), torch.tensor([1.0, 0.0, 0.0])
    over_black = rgb * alpha + black * (1 - alpha)
    torch.testing.assert_close(recomposited(over_black, alpha, black, red), rgb * alpha + red * (1 - alpha))
    torch.testing.assert_close(recomposited(over_black, alpha, black, white), rgb * alpha + (1 - alpha))
    assert recomposited(over_black, None, black, red) is over_black


def test_background_choice(demo, tmp_path):
    from ctgs.stages.train import resolve_config, scene_background

    ns = write_nerfstudio(demo, str(tmp_path / "ns"))
    blender = write_blender(ns, str(tmp_path / "blender"), TEST_NAMES, points=False)
    assert scene_background(demo, None, ()) == [] and scene_background(demo, "random", ()) == ["random"]
    assert scene_background(blender, None, ()) == ["white"]
    assert scene_background(blender, "random", ()) == ["white", "random"]
    assert scene_background(blender, "black", ()) == ["black"]
    assert scene_background(blender, None, ("background=[0.5, 0.5, 0.5]",)) == []
    cfg = resolve_config(blender, str(tmp_path / "run"), None, None, (), None, False, None, None, preset="fast",
                         backgrounds=["white", "random"])
    assert cfg.background == [1.0, 1.0, 1.0] and cfg.random_background
