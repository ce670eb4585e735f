"""`--images images_N` a scene lacks is made from images/ as `ctgs sfm` makes its pyramid, and kept."""

from __future__ import annotations

import os
import shutil
import stat

import numpy as np
import pytest

from ctgs.errors import UserError
from ctgs.io.images import image_info, read_image
from ctgs.scene import levels
from ctgs.scene.levels import level_dir
from ctgs.scene.loader import load_scene
from ctgs.scene.sfm import build_pyramid


def test_missing_level_is_made_in_the_scene_and_kept(tiny_demo, tmp_path, capsys):
    scene = str(tiny_demo)
    assert not os.path.isdir(os.path.join(scene, "images_2"))
    s = load_scene(scene, images="images_2", holdout=8)
    made = os.path.join(scene, "images_2")
    assert os.path.isdir(made) and "making it from images/" in capsys.readouterr().err
    full = load_scene(scene, images="images", holdout=8)
    # half the size (round(W / 2)), cameras rescaled to it, pixels as OpenImageIO's antialiased resize gives them
    assert (s.train[0].camera.width, s.train[0].camera.height) == (32, 24)
    assert abs(s.train[0].camera.fx - full.train[0].camera.fx / 2) < 1e-4
    # the very pixels `ctgs sfm` writes for its pyramid
    twin = shutil.copytree(os.path.join(scene, "images"), tmp_path / "twin" / "images")
    build_pyramid(str(twin.parent), factors=(2,))
    for name in os.listdir(made):
        assert np.array_equal(read_image(os.path.join(made, name)), read_image(str(twin.parent / "images_2" / name)))
    # kept: a second load makes nothing and says nothing
    load_scene(scene, images="images_2", holdout=8)
    assert capsys.readouterr().err == ""
    assert not [d for d in os.listdir(scene) if d.startswith(".images_2")]  # no temporary left


def test_read_only_scene_keeps_its_level_in_the_cache(tiny_demo, tmp_path, monkeypatch):
    if os.geteuid() == 0:
        # root writes through permission bits: stand the probe in for a read-only folder
        monkeypatch.setattr("ctgs.scene.levels._writable", lambda folder: False)
    scene = str(tiny_demo)
    monkeypatch.setenv("CTGS_CACHE_DIR", str(tmp_path / "cache"))
    os.chmod(scene, stat.S_IRUSR | stat.S_IXUSR)
    try:
        path = level_dir(scene, "images_4", quiet=True)
    finally:
        os.chmod(scene, 0o755)
    assert path.startswith(str(tmp_path / "cache")) and not os.path.isdir(os.path.join(scene, "images_4"))
    assert image_info(os.path.join(path, sorted(os.listdir(path))[0])).width == 16
    assert level_dir(scene, "images_4", quiet=True) == path  # found again, not made again


def test_unknown_folder_still_names_what_exists(tiny_demo):
    with pytest.raises(UserError, match="image folder not found; available: images"):
        load_scene(str(tiny_demo), images="photos", holdout=8)


def test_two_runs_making_one_level_at_once_both_use_it(tiny_demo, monkeypatch):
    """Two trainings started together on a scene lacking images_2 both made it; the one that renamed second failed
    with "already exists". Here the other run makes the whole level while this one is writing its first image."""
    scene = str(tiny_demo)
    real_write = levels.write_image
    other = {}

    def write_while_another_run_finishes(path, *args, **kwargs):
        if not other:
            other["started"] = True
            other["path"] = level_dir(scene, "images_2", quiet=True)  # the other run, start to end
        return real_write(path, *args, **kwargs)

    monkeypatch.setattr(levels, "write_image", write_while_another_run_finishes)
    path = level_dir(scene, "images_2", quiet=True)
    assert path == other["path"] == os.path.join(scene, "images_2")
    assert sorted(os.listdir(path)) == sorted(os.listdir(os.path.join(scene, "images")))
    assert not [d for d in os.listdir(scene) if d.startswith(".images_2")]  # this run's temporary is gone
