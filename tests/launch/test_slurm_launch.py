"""`make all LAUNCHER=slurm` against a real Slurm (a one-node cluster on localhost, conftest.py): two tiny scenes
through the job array and the table job; a job signalled as Slurm does before a time limit requeues itself and
resumes from its checkpoint. Without Slurm (or root) those two skip, saying why; the rest needs no cluster."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from ctgs.launch import slurm as launch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
VENV = os.path.dirname(os.path.dirname(sys.executable))
MANIFEST = """name = "tinyset"
holdout = 4
images = "images"

[archives.none]
url = "http://127.0.0.1:9/none.zip"

[scenes.tinya]
archive = "none"

[scenes.tinyb]
archive = "none"
"""
# both tests: the requeued run is compared with the uninterrupted one (the fast preset checkpoints every 40 here)
ITERATIONS = 400


def _make(*args, env, timeout=600):
    # -o: the venv is taken as it is (`make test` made it); GPUS=0: the test node has none
    cmd = ["make", "--no-print-directory", "-C", ROOT, "-o", f"{VENV}/.installed", *args, f"VENV={VENV}"]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A tiny scene and a manifest listing it twice (tinya, tinyb)."""
    from ctgs.scene.demo import make_demo_scene

    base = tmp_path_factory.mktemp("sweep")
    scene = make_demo_scene(str(base / "scene"), num_views=8, width=64, height=48, points=300)
    (base / "manifests").mkdir()
    (base / "manifests" / "tinyset.toml").write_text(MANIFEST)
    return base, scene


def _sweep_args(base, scene, runs, scenes):
    return ["all", "LAUNCHER=slurm", f"SCENES={' '.join(scenes)}", f"RUNS={runs}", f"ITERATIONS={ITERATIONS}",
            "PRESET=fast", "BACKEND=cpu", "GPUS=0", "CPUS=1", "MEM=1G",
            "TIME_LIMIT=00:20:00", *[f"SCENE_DIR_{s}={scene}" for s in scenes]]


def _env(slurm, base):
    return slurm.env({**os.environ, "CTGS_MANIFEST_DIR": str(base / "manifests"), "OMP_NUM_THREADS": "1"})


@pytest.fixture(scope="module")
def sweep(slurm, work):
    """The two scenes through `make all LAUNCHER=slurm SLURM_WAIT=1`: (runs folder, make's result, wall seconds)."""
    base, scene = work
    runs = base / "runs"
    t0 = time.monotonic()
    r = _make(*_sweep_args(base, scene, runs, ["tinya", "tinyb"]), "SLURM_WAIT=1", env=_env(slurm, base))
    return runs, r, time.monotonic() - t0


@pytest.mark.slow
def test_two_scenes_through_slurm_end_in_one_table(slurm, work, sweep):
    base, scene = work
    runs, r, wall = sweep
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:] + slurm.logs()
    print(f"\ntwo scenes through Slurm (submit, 2 array tasks, table job, wait): {wall:.1f} s wall")
    print(r.stdout[r.stdout.index("tinya: submitted"):])
    jobs = json.loads((runs / "slurm" / "jobs.json").read_text())
    assert set(jobs["scenes"]) == {"tinya", "tinyb"} and jobs["table"]
    table = (runs / "table" / "table.md").read_text()
    assert any(line.startswith("| tinyset | tinya |") for line in table.splitlines()), table
    assert any(line.startswith("| tinyset | tinyb |") for line in table.splitlines()), table
    assert (runs / "table-compressed" / "table.md").is_file()
    for s in ("tinya", "tinyb"):
        log = (runs / s / "slurm.log").read_text()
        assert f"{launch.MARK} scene {s}, job" in log and f"{launch.MARK} {s} finished" in log, log[-2000:]
    status = _make("status", f"RUNS={runs}", env=_env(slurm, base))
    assert status.returncode == 0 and [line.split()[:2] for line in status.stdout.splitlines()] == [
        ["tinya", "done"], ["tinyb", "done"], ["table", "done"]], status.stdout + status.stderr
    # the same command again submits nothing: both scenes are finished
    again = _make(*_sweep_args(base, scene, runs, ["tinya", "tinyb"]), env=_env(slurm, base))
    assert again.returncode == 0, again.stderr
    assert "tinya: finished" in again.stdout and "tinyb: finished" in again.stdout
    assert "submitted as job" not in again.stdout
    # what sbatch refuses (here a partition the cluster lacks) is one line naming where the options come from
    bad = _make(*_sweep_args(base, scene, base / "runs-bad", ["tinya"]), "PARTITION=nosuch", env=_env(slurm, base))
    assert bad.returncode != 0
    assert bad.stderr.startswith("error: sbatch refused: invalid partition specified: nosuch (the options come from "
                                 "SLURM_TOML and PARTITION="), bad.stderr


@pytest.mark.slow
def test_a_job_signalled_before_its_time_limit_requeues_and_resumes(slurm, work, sweep):
    """TERM to the batch shell, as --signal=B:TERM@N does: the training stops at its checkpoint, the job requeues
    itself, the requeued job resumes; the model ends as the uninterrupted run's (tinya of the sweep) did."""
    base, scene = work
    runs = base / "runs-requeue"
    env = _env(slurm, base)
    t0 = time.monotonic()
    r = _make(*_sweep_args(base, scene, runs, ["tinya"]), env=env)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    job = json.loads((runs / "slurm" / "jobs.json").read_text())["scenes"]["tinya"]
    ckpt = runs / "tinya" / "checkpoints"
    end = time.monotonic() + 300
    while not (ckpt / "prev.pt").exists():  # a second checkpoint written: mid-training, past the first
        assert time.monotonic() < end, (runs / "tinya" / "slurm.log").read_text()[-3000:] + slurm.logs()
        assert not (runs / "tinya" / "model.pt").exists(), "the training ended before the test could signal it"
        time.sleep(0.05)
    subprocess.run(["scancel", "--batch", "--signal=TERM", job], env=env, check=True, timeout=30)
    ids = [job, json.loads((runs / "slurm" / "jobs.json").read_text())["table"]]
    end = time.monotonic() + 400
    while any(st in launch.QUEUED for st, _ in _states(ids, env).values()):
        assert time.monotonic() < end, (runs / "tinya" / "slurm.log").read_text()[-3000:] + slurm.logs()
        time.sleep(1)
    wall = time.monotonic() - t0
    log = (runs / "tinya" / "slurm.log").read_text()
    print(f"\nrequeue test: submit, TERM, requeue, resume, table: {wall:.1f} s wall")
    print("\n".join(line for line in log.splitlines() if line.startswith(launch.MARK) or line.startswith("done:")))
    assert "TERM from Slurm" in log and f"{launch.MARK} requeueing job" in log, log[-3000:]
    assert ", restart 1," in log, log[-3000:]
    resumed_at = int(log.split("from the checkpoint at iteration ")[1].split()[0])
    assert 0 < resumed_at < ITERATIONS
    assert f"{launch.MARK} tinya finished" in log and (runs / "table" / "table.md").is_file(), log[-3000:]
    # the same shape as the uninterrupted run (on a CPU a resumed run is bit-identical), and the same quality
    import torch

    def shapes(path):
        model = torch.load(path, map_location="cpu", weights_only=True)["model"]
        return {k: tuple(v.shape) for k, v in model.items() if hasattr(v, "shape")}

    whole = sweep[0] / "tinya"
    assert shapes(runs / "tinya" / "model.pt") == shapes(whole / "model.pt")
    psnr = [json.loads((d / "eval" / "metrics.json").read_text()) for d in (runs / "tinya", whole)]
    assert psnr[0]["psnr"] == pytest.approx(psnr[1]["psnr"], abs=0.05)


def _states(ids, env):
    out = {}
    r = subprocess.run(["squeue", "-h", "-r", "-j", ",".join(ids), "-o", "%i|%T"], env=env, capture_output=True,
                       text=True)
    for line in r.stdout.split():
        jid, st = line.split("|")
        out[jid] = (st, "")
    return out


# ---- no cluster needed -------------------------------------------------------------------------------------------

def test_an_unknown_launcher_is_one_line(tmp_path):
    r = _make("all", "SCENES=tinya", "LAUNCHER=kubernetes", f"RUNS={tmp_path}", env=dict(os.environ))
    assert r.returncode == 2
    assert "LAUNCHER=kubernetes: unknown launcher; use LAUNCHER=slurm" in r.stderr


def test_options_file_errors_name_the_file_and_key(tmp_path):
    bad = tmp_path / "slurm.toml"
    bad.write_text("[scene]\npartiton = 'gpu'\n")
    with pytest.raises(launch.UserError, match=f"{bad}: unknown key 'partiton' in \\[scene\\]"):
        launch.load_options(str(bad))
    bad.write_text("[scene]\ngpus = '1'\n")
    with pytest.raises(launch.UserError, match="gpus = '1' should be a int"):
        launch.load_options(str(bad))
    with pytest.raises(launch.UserError, match="Slurm options file not found"):
        launch.load_options(str(tmp_path / "nope.toml"))
    shipped = launch.load_options(os.path.join(ROOT, "configs", "slurm", "defaults.toml"))
    assert shipped == launch.DEFAULTS and shipped["scene"]["gpus"] == 1


def test_without_sbatch_the_submission_says_so(tmp_path):
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "tinyset.toml").write_text(MANIFEST)
    env = {**os.environ, "PATH": str(tmp_path / "empty"), "CTGS_MANIFEST_DIR": str(tmp_path / "m")}
    r = subprocess.run([sys.executable, "-m", "ctgs.launch.slurm", "submit", "--scenes", "tinya",
                        "--runs", str(tmp_path / "runs")], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.startswith("error: sbatch: not found; LAUNCHER=slurm needs"), r.stderr
    r = subprocess.run([sys.executable, "-m", "ctgs.launch.slurm", "submit", "--scenes", "nosuch",
                        "--runs", str(tmp_path / "runs")], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "no manifest lists a scene 'nosuch'" in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", "ctgs.launch.slurm", "submit", "--scenes", "tinya", "--gpus", "one",
                        "--runs", str(tmp_path / "runs")], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "GPUS=one: should be a whole number" in r.stderr, r.stderr


def test_status_from_the_files_alone(tmp_path):
    runs = tmp_path / "runs"
    for f in launch.FINISHED:
        (runs / "a" / f).parent.mkdir(parents=True, exist_ok=True)
        (runs / "a" / f).write_text("{}")
    (runs / "b" / "checkpoints").mkdir(parents=True)
    (runs / "b" / "slurm.log").write_text(f"{launch.MARK} scene b\nerror: out of memory\n"
                                          "make: *** [Makefile:80: runs/b/model.pt] Error 1\n"
                                          f"{launch.MARK} b failed (exit 2)\n")
    (runs / "slurm").mkdir()
    launch.write_jobs(str(runs), {"scenes": {"a": "7_0", "b": "7_1"}, "table": None})
    rows = launch.scene_states(str(runs), ["a", "b", "c"], launch.read_jobs(str(runs)))
    assert [r[:3] for r in rows] == [("a", "done", "7_0"), ("b", "failed", "7_1"), ("c", "not submitted", "")]
    assert rows[1][3].startswith("error: out of memory (")


def test_the_job_scripts_are_their_templates_filled_in(tmp_path):
    """The shipped templates (ctgs/launch/templates/) with every @NAME@ filled in, quoted for bash, and valid bash."""
    root, runs, scenes, make_args = "/clone of ctgs", "/runs/it's", ["bicycle", "garden"], ["PRESET=fast", "X=a b"]
    for name, text in (("scene.sh", launch._scene_script(root, runs, scenes, make_args, "/venv/bin/python")),
                       ("table.sh", launch._table_script(root, runs, scenes, make_args))):
        assert text.startswith("#!/bin/bash\n") and not launch.PLACEHOLDER.search(text), text
        assert "cd '/clone of ctgs'" in text and "'X=a b'" in text and "bicycle garden" in text
        (tmp_path / name).write_text(text)
        r = subprocess.run(["bash", "-n", str(tmp_path / name)], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
