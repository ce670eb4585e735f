"""The fault suite's starting point: one tiny finished pipeline per session (scene, run, model, compressed model),
a few seconds to make. Cases that damage a file restore it (fault_helpers.damaged) or work on copies."""

from __future__ import annotations

import os
import shutil

import pytest

from fault_helpers import GAUSSIAN_FILES, SCENE_OPTS, TRAIN_OPTS, cli


def _ok(args: list[str]) -> None:
    result = cli(args)
    assert result.exit_code == 0, (args, result.output, result.stderr)


@pytest.fixture(scope="session")
def pipeline(tmp_path_factory) -> dict:
    root = str(tmp_path_factory.mktemp("pipeline"))
    p = {"root": root, "scene": f"{root}/scene", "run": f"{root}/run", "model": f"{root}/run/model",
         "small": f"{root}/run/small", "web": f"{root}/run/webmodel/web"}
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _ok(["demo-scene", p["scene"], *SCENE_OPTS])
    # photos for sfm: 12 views of 128x96 (what tests/test_cli_chain.py reconstructs; ~3 s of SfM)
    _ok(["demo-scene", f"{root}/photos", "--views", "12", "--width", "128", "--height", "96", "--points", "500"])
    p["photos"] = f"{root}/photos/images"
    _ok(["train", p["scene"], "-o", p["run"], *TRAIN_OPTS])
    _ok(["export", p["run"], "-o", p["model"]])
    _ok(["compress", p["model"], "-o", p["small"]])
    _ok(["export", p["run"], "--format", "web", "-o", f"{root}/run/webmodel"])
    assert os.path.isfile(f"{p['web']}/atlas_000.bin"), "the tiny run has no texels: the atlas cases need some"
    _ok(["eval", p["run"], "--no-lpips"])  # run/eval/metrics.json, for eval --table
    for fmt, ext in GAUSSIAN_FILES.items():  # the files for Gaussian viewers, which eval --model reads back
        _ok(["export", p["run"], "--format", fmt, "-o", f"{root}/run/m.{ext}"])
    # the scene again with its COLMAP model as text files (what other tools often ship)
    from ctgs.scene.colmap import import_pycolmap

    p["textscene"] = shutil.copytree(p["scene"], f"{root}/textscene")
    sparse = f"{root}/textscene/sparse/0"
    import_pycolmap().Reconstruction(sparse).write_text(sparse)
    for name in os.listdir(sparse):
        if name.endswith(".bin"):
            os.remove(os.path.join(sparse, name))
    return p
