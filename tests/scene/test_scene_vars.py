"""`python -m ctgs.scene.scene_vars SCENE` (the Makefile's per-scene facts): known scenes, and a refusal to guess."""

from __future__ import annotations

import subprocess
import sys

import pytest

from ctgs.errors import UserError
from ctgs.scene.scene_vars import scene_vars

ARCHIVE = '[archives.a]\nurl = "https://example.invalid/a.zip"\n'


def _run(*args, env=None):
    return subprocess.run([sys.executable, "-m", "ctgs.scene.scene_vars", *args], capture_output=True, text=True,
                          env=env)


def test_known_scenes_come_from_the_manifests():
    assert scene_vars("bicycle") == ("mipnerf360", "images_4", 8)
    assert scene_vars("room") == ("mipnerf360", "images_2", 8)
    assert scene_vars("truck") == ("tandt", "images", 8)
    r = _run("drjohnson")
    assert r.returncode == 0 and r.stdout.split() == ["deepblending", "images", "8", "db/drjohnson"]


def test_unknown_scene_is_one_error_listing_the_known_scenes():
    r = _run("bicylce")
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "'bicylce'" in lines[0] and "Traceback" not in r.stderr
    for scene in ("bicycle", "garden", "truck", "playroom"):
        assert scene in lines[0]


def test_a_scene_in_two_manifests_is_refused(tmp_path):
    for name in ("one", "two"):
        (tmp_path / f"{name}.toml").write_text(f'name = "{name}"\n{ARCHIVE}[scenes.same]\narchive = "a"\n')
    with pytest.raises(UserError, match="several datasets"):
        scene_vars("same", str(tmp_path))
    with pytest.raises(UserError, match="known scenes: same"):
        scene_vars("other", str(tmp_path))


def test_usage():
    r = _run()
    assert r.returncode == 2 and "usage" in r.stderr
