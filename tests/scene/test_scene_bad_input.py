"""Bad input: each case ends with one clear line naming the file/cause, a non-zero exit, and no
half-written SCENE_DIR (or work folder) left behind."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pycolmap
import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.io.images import write_image
from ctgs.scene import load_scene


def _noise(path, w=64, h=48, seed=0):
    write_image(str(path), np.random.default_rng(seed).random((h, w, 3)).astype(np.float32))


def _run_sfm(images_dir, scene_dir):
    result = CliRunner().invoke(main, ["sfm", str(images_dir), "-o", str(scene_dir), "--threads", "1"])
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    return result.exit_code, lines


def _assert_clean_failure(tmp_path, scene_dir, code, lines, *needles):
    assert code != 0
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1 and len(lines) == 1, lines
    for needle in needles:
        assert needle in errors[0], errors[0]
    assert not os.path.exists(scene_dir)
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")], "work folder left behind"


def test_missing_folder(tmp_path):
    code, lines = _run_sfm(tmp_path / "nope", tmp_path / "out")
    _assert_clean_failure(tmp_path, tmp_path / "out", code, lines, "nope", "not found")


def test_empty_folder(tmp_path):
    (tmp_path / "imgs").mkdir()
    (tmp_path / "imgs" / "readme.txt").write_text("no images here")
    code, lines = _run_sfm(tmp_path / "imgs", tmp_path / "out")
    _assert_clean_failure(tmp_path, tmp_path / "out", code, lines, "imgs", "no images")


def test_fewer_than_three_images(tmp_path):
    for i in range(2):
        _noise(tmp_path / "imgs" / f"{i}.png", seed=i)
    code, lines = _run_sfm(tmp_path / "imgs", tmp_path / "out")
    _assert_clean_failure(tmp_path, tmp_path / "out", code, lines, "only 2 image", "at least 3")


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_corrupt_image(tmp_path, damage):
    for i in range(4):
        _noise(tmp_path / "imgs" / f"{i}.png", w=128, h=96, seed=i)
    bad = tmp_path / "imgs" / "2.png"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 3] if damage == "truncated" else b"\x89PNG garbage" * 50)
    code, lines = _run_sfm(tmp_path / "imgs", tmp_path / "out")
    _assert_clean_failure(tmp_path, tmp_path / "out", code, lines, "2.png", "replace or remove")


def test_mixed_sizes(tmp_path):
    for i in range(3):
        _noise(tmp_path / "imgs" / f"{i}.png", seed=i)
    _noise(tmp_path / "imgs" / "3.png", w=80, h=48)
    code, lines = _run_sfm(tmp_path / "imgs", tmp_path / "out")
    _assert_clean_failure(tmp_path, tmp_path / "out", code, lines, "3.png", "80x48", "one size")


def test_sfm_registering_too_few_images(tmp_path, tiny_demo_master):
    """Unrelated noise pictures: nothing (or too little) registers; the work folder is removed too."""
    for i in range(5):
        _noise(tmp_path / "imgs" / f"{i}.png", w=96, h=72, seed=i)
    code, lines = _run_sfm(tmp_path / "imgs", tmp_path / "out")
    _assert_clean_failure(tmp_path, tmp_path / "out", code, lines, "imgs", "register")


def test_scene_dir_that_is_something_else_is_not_touched(tmp_path):
    for i in range(3):
        _noise(tmp_path / "imgs" / f"{i}.png", seed=i)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "precious.txt").write_text("keep me")
    code, lines = _run_sfm(tmp_path / "imgs", tmp_path / "out")
    assert code != 0 and "--force" in lines[-1]
    assert os.listdir(tmp_path / "out") == ["precious.txt"]


def test_input_folder_that_would_be_overwritten(tmp_path):
    for i in range(3):
        _noise(tmp_path / "scene" / "images" / f"{i}.png", seed=i)
    result = CliRunner().invoke(main, ["sfm", str(tmp_path / "scene" / "images"), "-o", str(tmp_path / "scene")])
    assert result.exit_code == 2 and "scene/input" in result.stderr
    assert sorted(os.listdir(tmp_path / "scene")) == ["images"]


# ---- load_scene (used by train/eval): UserError with one line naming the file and the fix ----

def _one_line_error(fn, *needles) -> str:
    with pytest.raises(UserError) as err:
        fn()
    message = str(err.value)
    assert "\n" not in message
    for needle in needles:
        assert needle in message, message
    return message


def test_loader_missing_scene_and_image_folder(tmp_path, tiny_demo):
    _one_line_error(lambda: load_scene(str(tmp_path / "absent")), "absent", "not found")
    # (a missing images_N is made from images/: ctgs.scene.levels, tests/scene/test_levels.py)
    _one_line_error(lambda: load_scene(tiny_demo, images="photos_4"), "photos_4", "available: images")
    shutil.rmtree(os.path.join(tiny_demo, "sparse"))
    _one_line_error(lambda: load_scene(tiny_demo), "sparse", "ctgs sfm")


def test_loader_image_missing_on_disk(tiny_demo):
    os.remove(os.path.join(tiny_demo, "images", "004.png"))
    _one_line_error(lambda: load_scene(tiny_demo), "004.png", "missing on disk")


def test_loader_corrupt_image(tiny_demo):
    path = os.path.join(tiny_demo, "images", "003.png")
    with open(path, "rb") as f:
        data = f.read()
    with open(path, "wb") as f:
        f.write(data[: len(data) // 2])
    _one_line_error(lambda: load_scene(tiny_demo), "003.png", "corrupt")


def test_loader_wrong_image_size(tiny_demo):
    _noise(os.path.join(tiny_demo, "images", "005.png"), w=64, h=64)
    _one_line_error(lambda: load_scene(tiny_demo), "005.png", "64x64", "aspect")


def test_loader_zero_points_starts_from_random_points(tiny_demo):
    """A model without points: random points in the cube the cameras look at, said in the scene's meta."""
    sparse = os.path.join(tiny_demo, "sparse", "0")
    rec = pycolmap.Reconstruction(sparse)
    for point_id in list(rec.point3D_ids()):
        rec.delete_point3D(point_id)
    rec.write_binary(sparse)
    scene = load_scene(tiny_demo, load_images=False)
    assert scene.meta["points"] == "random" and "points3D" in scene.meta["points_note"]
    assert len(scene.points) == 100_000 and np.isfinite(scene.points).all()
    # the cameras look at the demo's target (0, 0.6, 0.6): the cube holds it
    lo, hi = scene.points.min(0), scene.points.max(0)
    assert np.all(lo < [0.0, 0.6, 0.6]) and np.all(hi > [0.0, 0.6, 0.6]) and np.all(hi - lo < 3.0)


def test_loader_unknown_camera_model(tiny_demo):
    sparse = os.path.join(tiny_demo, "sparse", "0")
    rec = pycolmap.Reconstruction(sparse)
    rec.cameras[1].model = "OPENCV"
    rec.cameras[1].params = [50.0, 50.0, 32.0, 24.0, 0.01, 0.0, 0.0, 0.0]
    rec.write_binary(sparse)
    _one_line_error(lambda: load_scene(tiny_demo), "OPENCV", "ctgs sfm")


def test_loader_corrupt_model_file(tiny_demo):
    with open(os.path.join(tiny_demo, "sparse", "0", "images.bin"), "wb") as f:
        f.write(b"\x01\x02\x03")
    _one_line_error(lambda: load_scene(tiny_demo), "images.bin: corrupt COLMAP images file")


def test_float_images_are_refused_by_sfm(tmp_path):
    for i in range(3):
        _noise(tmp_path / "imgs" / f"{i}.png", seed=i)
    _noise(tmp_path / "imgs" / "3.exr", seed=3)
    code, lines = _run_sfm(tmp_path / "imgs", tmp_path / "out")
    _assert_clean_failure(tmp_path, tmp_path / "out", code, lines, "3.exr", "PNG")
