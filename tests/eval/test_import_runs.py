"""benchmarks/device/import_runs.py: a run trained on the device comes back as run_NAME.tgz and becomes
benchmarks/paired.py's finished run here: pointed at this machine's scene, exported, evaluated, recorded."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile

import torch

from fixture_run import make_run

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCRIPT = os.path.join(ROOT, "benchmarks", "device", "import_runs.py")


def _device_tgz(run: str, files: str, name: str) -> str:
    """The fixture run as the device returns it: its scene named by a path that does not exist here."""
    state = torch.load(os.path.join(run, "model.pt"), weights_only=True)
    state["scene_dir"] = "/root/device/.gpu/scenes/demo"
    state["config"] = {"backend": "cuda", "scene_dir": "/root/device/.gpu/scenes/demo"}
    torch.save(state, os.path.join(run, "model.pt"))
    with open(os.path.join(run, "config.toml"), "w") as fh:
        fh.write('scene_dir = "/root/device/.gpu/scenes/demo"\nimages = "images"\nbackend = "cuda"\n')
    with open(os.path.join(run, "log.jsonl"), "w") as fh:
        fh.write('{"type": "test", "it": 10, "psnr": 10.0}\n')
    os.makedirs(files, exist_ok=True)
    tgz = os.path.join(files, f"run_{name}.tgz")
    with tarfile.open(tgz, "w:gz") as tf:
        for f in ("model.pt", "config.toml", "log.jsonl", "train_summary.json"):
            tf.add(os.path.join(run, f), arcname=f)
    return tgz


def test_a_device_run_is_imported_and_recorded(tmp_path):
    run = make_run(str(tmp_path / "fixture"))
    scene = torch.load(os.path.join(run, "model.pt"), weights_only=True)["scene_dir"]
    files = str(tmp_path / "files")
    _device_tgz(run, files, "fast_s3")
    status = {"jobs": {"fast_s3": {"state": "done", "wall_s": 77.0, "args": ["SCENE", "--preset", "fast"]}}}
    (tmp_path / "status.json").write_text(json.dumps(status))
    with tarfile.open(os.path.join(files, "checks.tgz"), "w:gz") as tf:
        tf.add(tmp_path / "status.json", arcname="./status.json")
    work = str(tmp_path / "work")
    r = subprocess.run([sys.executable, SCRIPT, files, "--work", work, "--scene", scene, "--commit", "abc1234"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    rec = json.load(open(os.path.join(work, "fast_s3", "paired_record.json")))
    assert rec["label"] == "fast" and rec["seed"] == 3 and rec["commit"] == "abc1234" and rec["wall_s"] == 77.0
    assert rec["command"] == "-m ctgs train SCENE --preset fast" and 5 < rec["psnr"] < 60
    assert set(rec["per_view_psnr"]) == {"000.png", "008.png"}
    metrics = json.load(open(os.path.join(work, "fast_s3", "eval", "metrics.json")))
    assert metrics["scene_dir"] == os.path.abspath(scene) and metrics["backend"] in ("cpu", "cuda")
    # imported once: a second call leaves it alone
    r = subprocess.run([sys.executable, SCRIPT, files, "--work", work, "--scene", scene, "--commit", "abc1234"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0 and "already imported" in r.stdout


def test_bad_names_and_empty_folders_are_named(tmp_path):
    run = make_run(str(tmp_path / "fixture"))
    files = str(tmp_path / "files")
    os.makedirs(files)
    args = ["--work", str(tmp_path / "w"), "--scene", str(tmp_path), "--commit", "x"]
    r = subprocess.run([sys.executable, SCRIPT, files, *args], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode != 0 and "no run_*.tgz" in r.stderr
    _device_tgz(run, files, "fastseed3")
    r = subprocess.run([sys.executable, SCRIPT, files, *args], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode != 0 and "LABEL_sSEED" in r.stderr
