"""`make all` and `make table` on a benchmark scene that is already on disk, as the benchmarks run (no network): a
tiny local scene named by SCENE_DIR_<scene>, listed by a manifest with a paper row, through train -> export ->
compress -> eval and the table with the paper's row beside ours. Marked slow (a few short trainings)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MANIFEST = """name = "tinyset"
holdout = 4
images = "images_2"

[archives.none]
url = "http://127.0.0.1:9/none.zip"

[scenes.tiny]
archive = "none"
paper = { ssim = 0.9, psnr = 30.0, lpips = 0.2, points = 1000, texels = 20000, params = 120000, fps = 99, mem_mb = 0.5, resolution = "64x48" }
"""


@pytest.mark.slow
def test_make_all_and_table_on_a_local_scene(tmp_path):
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    from ctgs.scene.demo import make_demo_scene

    scene = make_demo_scene(str(tmp_path / "somewhere" / "tiny-copy"), num_views=8, width=64, height=48, points=300)
    manifests = tmp_path / "manifests"
    manifests.mkdir()
    (manifests / "tinyset.toml").write_text(MANIFEST)
    venv = os.path.dirname(os.path.dirname(sys.executable))
    runs = tmp_path / "runs"
    env = {**os.environ, "CTGS_MANIFEST_DIR": str(manifests), "OMP_NUM_THREADS": "1"}
    # -o: the venv and the LPIPS weights are taken as they are (`make test` made them)
    cmd = ["make", "--no-print-directory", "-C", ROOT, "-o", f"{venv}/.installed", "table", "SCENES=tiny",
           f"SCENE_DIR_tiny={scene}", "ITERATIONS=60", "PRESET=fast", f"RUNS={runs}", f"VENV={venv}",
           "BACKEND=cpu", "CONFIG=", "COMPRESS_TARGET=balanced"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1200)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    # images_2 was made from images/ (the manifest asks for it; the scene had none) and kept beside it
    assert os.path.isdir(os.path.join(scene, "images_2"))
    for name in ("model.pt", "model/manifest.json", "model-compressed/manifest.json", "eval/metrics.json",
                 "eval-compressed/metrics.json"):
        assert (runs / "tiny" / name).is_file(), name
    table = (runs / "table" / "table.md").read_text()
    lines = table.splitlines()
    ours = next(line for line in lines if line.startswith("| tinyset | tiny |"))
    paper = next(line for line in lines if line.startswith("| tinyset | tiny (paper, all photos) |"))
    assert "| 32x24 |" in ours and "| 64x48 |" in paper and "| 30.00 |" in paper
    assert (runs / "table-compressed" / "table.md").is_file()
    # a second `make all` redoes nothing
    r2 = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert r2.returncode == 0 and "ctgs train" not in r2.stdout, r2.stdout[-2000:]


def test_a_scene_dir_that_does_not_exist_is_named(tmp_path):
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    venv = os.path.dirname(os.path.dirname(sys.executable))
    r = subprocess.run(["make", "--no-print-directory", "-C", ROOT, "-o", f"{venv}/.installed",
                        f"{tmp_path}/runs/bonsai/model.pt", f"SCENE_DIR_bonsai={tmp_path}/nowhere", f"RUNS={tmp_path}/runs",
                        f"VENV={venv}"], capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and f"SCENE_DIR_bonsai={tmp_path}/nowhere: no such folder" in r.stderr


@pytest.mark.slow
def test_a_data_root_laid_out_as_the_archive_and_a_scene_list_of_test_views(tmp_path):
    """DATA_ROOT holding the scene where the dataset's archive puts it (the manifest's path, e.g. db/playroom), with
    its own test_views.txt: `make` trains it from there, on those test views, and downloads nothing."""
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    import torch

    from ctgs.scene.demo import make_demo_scene

    root = tmp_path / "data"
    scene = make_demo_scene(str(root / "db" / "tiny"), num_views=8, width=64, height=48, points=300)
    with open(os.path.join(scene, "test_views.txt"), "w") as f:
        f.write("001.png\n006.png\nnot_registered.png\n")
    manifests = tmp_path / "manifests"
    manifests.mkdir()
    (manifests / "tinyset.toml").write_text(MANIFEST.replace('archive = "none"\n', 'archive = "none"\npath = "db/tiny"\n'))
    venv = os.path.dirname(os.path.dirname(sys.executable))
    runs = tmp_path / "runs"
    env = {**os.environ, "CTGS_MANIFEST_DIR": str(manifests), "OMP_NUM_THREADS": "1"}
    r = subprocess.run(["make", "--no-print-directory", "-C", ROOT, "-o", f"{venv}/.installed", f"{runs}/tiny/model.pt",
                        f"DATA_ROOT={root}", "ITERATIONS=20", "PRESET=fast", f"RUNS={runs}", f"VENV={venv}",
                        "BACKEND=cpu", "IMAGES=images"], env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "2 test views from test_views.txt, 6 training views" in r.stderr, r.stderr[-2000:]
    ckpt = torch.load(runs / "tiny" / "model.pt", weights_only=True)
    assert ckpt["scene_dir"] == scene and ckpt["test_views"] == ["001.png", "006.png"]
