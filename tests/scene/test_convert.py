"""`ctgs convert`: COLMAP -> nerfstudio -> COLMAP keeps cameras, points, names and masks; distorted photos leave
undistorted; the output folder is never half-written nor a folder that is not a converted scene."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.io.images import write_image
from ctgs.scene import load_scene

from scene_layouts import write_blender


def _convert(*args) -> str:
    result = CliRunner().invoke(main, ["convert", *args])
    assert result.exit_code == 0, result.output
    return result.output


def test_round_trip_through_nerfstudio(tiny_demo, tmp_path):
    mask = np.ones((48, 64))
    mask[:, 40:] = 0
    write_image(os.path.join(tiny_demo, "masks", "002.png"), mask)
    ns, back = str(tmp_path / "ns"), str(tmp_path / "back")
    level = tiny_demo / "images_2"
    level.mkdir()
    for name in os.listdir(tiny_demo / "images"):  # a level of another resampling than the one ctgs makes: copied
        write_image(str(level / name), np.full((24, 32, 3), 0.25))
    assert "nerfstudio: 10 views, 600 points" in _convert(str(tiny_demo), "--to", "nerfstudio", "-o", ns)
    with open(os.path.join(ns, "transforms.json")) as f:
        doc = json.load(f)
    assert doc["ply_file_path"] == "sparse_pc.ply" and doc["camera_model"] == "PINHOLE" and doc["w"] == 64
    assert [f for f in doc["frames"] if "mask_path" in f][0]["mask_path"] == "masks/002.png"
    assert "1 masks" in _convert(ns, "--to", "colmap", "-o", back)
    a, b = load_scene(str(tiny_demo)), load_scene(back)
    assert [v.name for v in a.train + a.test] == [v.name for v in b.train + b.test]
    for x, y in zip(a.train + a.test, b.train + b.test):
        np.testing.assert_allclose(y.camera.viewmat.numpy(), x.camera.viewmat.numpy(), atol=2e-7)
        assert (y.camera.fx, y.camera.cx) == pytest.approx((x.camera.fx, x.camera.cx))
        np.testing.assert_array_equal(y.image, x.image)
        assert (x.mask is None) == (y.mask is None)
        if x.mask is not None:
            np.testing.assert_array_equal(x.mask, y.mask)
    np.testing.assert_allclose(b.points, a.points, atol=1e-6)
    assert os.listdir(os.path.join(ns, "images_2")) == os.listdir(level)
    np.testing.assert_allclose(load_scene(ns, images="images_2").train[0].image, 64 / 255)


def test_blender_to_colmap_says_what_is_lost(tiny_demo, tmp_path):
    ns = str(tmp_path / "ns")
    _convert(str(tiny_demo), "--to", "nerfstudio", "-o", ns)
    blender = write_blender(ns, str(tmp_path / "blender"), {"000.png", "008.png"}, points=False)
    out = _convert(blender, "--to", "colmap", "-o", str(tmp_path / "colmap"))
    assert "0 points" in out and "random points" in out  # no points in, none out
    s = load_scene(str(tmp_path / "colmap"), load_images=False)
    assert s.meta["points"] == "random" and {v.name for v in s.test} == {"test_000.png", "train_007.png"}


def test_output_folder_rules(tiny_demo, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    result = CliRunner().invoke(main, ["convert", str(tiny_demo), "--to", "nerfstudio", "-o", str(out)])
    assert result.exit_code != 0 and "not empty" in result.output and (out / "notes.txt").exists()
    result = CliRunner().invoke(main, ["convert", str(tiny_demo), "--to", "nerfstudio", "-o", str(out), "--force"])
    assert result.exit_code != 0 and "not a converted scene" in result.output and (out / "notes.txt").exists()
    result = CliRunner().invoke(main, ["convert", str(tiny_demo), "--to", "colmap", "-o", str(tiny_demo), "--force"])
    assert result.exit_code != 0 and "would replace the scene" in result.output
    done = str(tmp_path / "done")
    _convert(str(tiny_demo), "--to", "nerfstudio", "-o", done)
    _convert(str(tiny_demo), "--to", "colmap", "-o", done, "--force")  # an earlier converted scene: replaced
    assert os.path.isdir(os.path.join(done, "sparse", "0"))
    assert not os.path.exists(os.path.join(done, "transforms.json"))
