"""A training stopped at any moment resumes or starts cleanly: the Makefile asks for a readable checkpoint (not a
checkpoints/ folder), a stop before the first checkpoint leaves no folder that looks resumable, the first checkpoint
comes by the clock (a kill -9 loses at most a minute or so), a TERM while the interpreter exits prints nothing, and a
training under random kill -9s ends with the uninterrupted run's model (benchmarks/crash_consistency.py, short)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch

from fault_helpers import TRAIN_OPTS, cli, tiny_manifest

from ctgs.errors import Terminated
from ctgs.runs.checkpoint import main as probe, previous_path, readable_checkpoint
from ctgs.train.loop import progress

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
import crash_consistency  # noqa: E402

def _stopped_job_folder(run: str) -> None:
    """What a Slurm job stopped by TERM before the first checkpoint left (before stops cleaned up): its log, the
    training's config and log, and an empty checkpoints/."""
    os.makedirs(os.path.join(run, "checkpoints"))
    for name, text in (("slurm.log", "== ctgs slurm: scene tiny\n"), ("config.toml", "seed = 0\n"), ("log.jsonl", "")):
        with open(os.path.join(run, name), "w") as fh:
            fh.write(text)


def test_the_makefile_resumes_a_readable_checkpoint_not_a_folder(pipeline, tmp_path, capsys):
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    runs = tmp_path / "runs"
    _stopped_job_folder(str(runs / "tiny"))
    assert probe([str(runs / "tiny")]) == 0 and capsys.readouterr().out == ""  # no --resume for this one
    venv = os.path.dirname(os.path.dirname(sys.executable))
    env = {**os.environ, "CTGS_MANIFEST_DIR": tiny_manifest(str(tmp_path / "manifests")), "OMP_NUM_THREADS": "1"}
    r = subprocess.run(["make", "--no-print-directory", "-C", ROOT, "-o", f"{venv}/.installed", f"VENV={venv}",
                        f"RUNS={runs}", f"SCENE_DIR_tiny={pipeline['scene']}", "ITERATIONS=20", "PRESET=fast",
                        "BACKEND=cpu", "CONFIG=", f"{runs}/tiny/model.pt"], env=env, capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "--resume" not in r.stdout and (runs / "tiny" / "model.pt").is_file()
    assert probe([str(runs / "tiny")]) == 0 and capsys.readouterr().out.strip() == "--resume"  # its last checkpoint


def test_a_cut_checkpoint_is_not_one_to_resume(tmp_path, capsys):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    torch.save({"model": {}, "iteration": 7}, run / "checkpoints" / "last.pt")
    assert readable_checkpoint(str(run)) == (str(run / "checkpoints" / "last.pt"), 7)
    data = (run / "checkpoints" / "last.pt").read_bytes()
    (run / "checkpoints" / "last.pt").write_bytes(data[: len(data) // 2])
    assert readable_checkpoint(str(run)) is None
    assert probe([str(run)]) == 0 and capsys.readouterr().out == ""
    assert (run / "checkpoints" / "last.pt").read_bytes() == data[: len(data) // 2]  # asked, not changed


def test_a_stop_before_the_first_checkpoint_leaves_nothing_resumable(pipeline, tmp_path, monkeypatch):
    """TERM while the training starts (a cluster's time limit while the extension compiled), in a folder the job
    made: no empty checkpoints/ stays to make the next start pass --resume."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "slurm.log").write_text("== ctgs slurm: scene tiny\n")

    def stopped(trainer, quiet):
        raise Terminated()

    monkeypatch.setattr(progress, "run_with_progress", stopped)
    result = cli(["train", pipeline["scene"], "-o", str(run), *TRAIN_OPTS])
    assert result.exit_code == 143 and "stopped before the first checkpoint" in result.stderr
    assert not (run / "checkpoints").exists() and (run / "slurm.log").is_file()
    assert readable_checkpoint(str(run)) is None


@pytest.mark.parametrize(("first_s", "every_s", "prev_it"), [(1e-6, 0, 2), (0, 1e-6, 19), (0, 0, None)])
def test_checkpoints_by_the_clock(first_s, every_s, prev_it, pipeline, tmp_path):
    """checkpoint_every = 0 (iterations: only at the end): the clock's checkpoints are what a kill -9 would resume
    from (the clock starts at the first step); the end's checkpoint rotates the last of them into prev.pt."""
    run = str(tmp_path / "run")
    opts = [o if o != "30" else "20" for o in TRAIN_OPTS] + ["--set", "checkpoint_every=0", "--set",
                                                            f"checkpoint_first_s={first_s}", "--set",
                                                            f"checkpoint_every_s={every_s}"]
    assert cli(["train", pipeline["scene"], "-o", run, *opts]).exit_code == 0
    prev = previous_path(run)
    if prev_it is None:
        assert not os.path.exists(prev)
    else:
        assert torch.load(prev, weights_only=True)["iteration"] == prev_it


def test_a_term_while_the_interpreter_exits_is_not_a_traceback(tmp_path):
    """A cluster sends TERM again at its time limit: once the stage is over, it ends the process as the signal does,
    not as an exception raised inside an exit handler."""
    code = ("import atexit, sys, time; atexit.register(time.sleep, 30); from ctgs.cli import main; "
            "sys.argv[0] = 'ctgs'; main()")
    proc = subprocess.Popen([sys.executable, "-c", code, "render", str(tmp_path / "none"), "-o", str(tmp_path / "o")],
                            stderr=subprocess.PIPE, text=True)
    first = proc.stderr.readline()  # the stage's error line: the stage is over, the exit handlers run
    assert first.startswith("error: "), first
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    rest = proc.communicate(timeout=60)[1]
    assert proc.returncode == -signal.SIGTERM and rest == "", rest


def test_random_kills_end_at_the_uninterrupted_model(tmp_path):
    """The short form of benchmarks/crash_consistency.py (its record: 20 kills): 2 kills at random moments."""
    opts = crash_consistency.parse(["--work", str(tmp_path), "--kills", "2", "--iterations", "24", "--views", "8",
                                    "--width", "48", "--height", "32", "--points", "300", "--seed", "1"])
    res = crash_consistency.run_check(str(tmp_path), opts)
    assert len(res["kills"]) == 2, res
    assert res["identical"], (res["tensor_diffs"], res["logs_equal"], res["kills"])
