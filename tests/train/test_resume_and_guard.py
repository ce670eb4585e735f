"""--resume reproduces an uninterrupted run (also after kill -9); the NaN/Inf guard stops cleanly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from ctgs.errors import Terminated, UserError
from ctgs.runs import load_run, training_scene
from ctgs.scene.demo import make_demo_scene
from ctgs.stages.train import train_main
from ctgs.stages.train import resolve_config
from ctgs.train.events import Step
from ctgs.train.loop.trainer import Trainer, TrainingDiverged
from train_helpers import run_log

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# 60 iterations at paper scale x 0.04: texture start at 20, checkpoints at 30, a full routine at 40
# (routine_margin=0; split threshold 2 texels and texel exponents down to 0, so it splits and upscales),
# texture reallocations every 10 (50 and 60 change the allocation). Log every step.
ROUTINE_AT = 40
SETS = ("iterations=60", "schedule_scale=0.04", "checkpoint_every=750", "backend='cpu'", "max_init_points=200",
        "threads=1", "routine_margin=0", "tau_tr_start=2.0", "tau_tr_end=2.0", "min_t2p_exp=0", "start_texels=4.0",
        "log_every=1")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(str(tmp_path_factory.mktemp("scene") / "demo"), num_views=10, width=48, height=36,
                           points=300)


@pytest.fixture(scope="module")
def reference_run(scene, tmp_path_factory):
    run = str(tmp_path_factory.mktemp("runs") / "full")
    train_main(scene, run, preset="fast", sets=SETS, quiet=True)
    return run


def _same_models(a, b):
    """Bit for bit: the CPU backend on one thread is deterministic, and a checkpoint holds all state."""
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for name, value in sa.items():
        if isinstance(value, torch.Tensor):
            assert value.dtype == sb[name].dtype and torch.equal(value, sb[name]), name
        else:
            assert value == sb[name], name


def test_resume_across_a_full_routine_is_bit_identical(scene, reference_run, tmp_path):
    run = str(tmp_path / "interrupted")
    cfg = resolve_config(scene, run, None, None, SETS, None, False, None, None, preset="fast")
    trainer = Trainer(cfg, training_scene(cfg), run)
    from ctgs.runs import write_config

    write_config(run, cfg.to_dict())
    gen = trainer.run()
    for ev in gen:  # run past the full routine, then stop without any cleanup (as a kill would)
        if isinstance(ev, Step) and ev.it == ROUTINE_AT + 5:
            break
    gen.close()
    state = torch.load(os.path.join(run, "checkpoints", "last.pt"), weights_only=True)
    assert state["iteration"] < ROUTINE_AT and not os.path.exists(os.path.join(run, "model.pt"))
    train_main(scene, run, resume=True, quiet=True)
    a, b = load_run(run), load_run(reference_run)
    assert a.iteration == 60
    _same_models(a.model, b.model)
    log, ref = run_log(run), run_log(reference_run)
    assert log == ref
    # What the resumed part went through, from its log: a full routine that split and upscaled, and a
    # texture reallocation (outside any routine) that changed the allocation.
    routine = next(r for r in log if r["type"] == "routine" and r["kind"] == "full")
    assert routine["it"] == ROUTINE_AT > state["iteration"]
    assert routine["split"] > 0 and routine["upscaled"] > 0 and routine["downscaled"] > 0, routine
    texels = {r["it"]: r["texels"] for r in log if r["type"] == "step"}
    realloc = [it for it in range(ROUTINE_AT + 10, 61, 10) if texels[it] != texels[it - 1]]
    assert realloc, texels


@pytest.mark.slow
def test_resume_after_kill_9(scene, reference_run, tmp_path):
    run = str(tmp_path / "killed")
    args = [sys.executable, "-m", "ctgs.cli", "train", scene, "-o", run, "--preset", "fast", "-q"]
    for s in SETS:
        args += ["--set", s]
    proc = subprocess.Popen(args, cwd=ROOT)
    ckpt = os.path.join(run, "checkpoints", "last.pt")
    deadline = time.time() + 300
    while not os.path.exists(ckpt) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert os.path.exists(ckpt) and not os.path.exists(os.path.join(run, "model.pt"))
    r = subprocess.run(args + ["--resume"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    _same_models(load_run(run).model, load_run(reference_run).model)


def test_nan_guard_stops_and_keeps_last_checkpoint(scene, tmp_path):
    run = str(tmp_path / "nan")
    with pytest.raises(TrainingDiverged, match=r"NaN/Inf in loss at iteration 35.*iteration 30"):
        train_main(scene, run, preset="fast", sets=SETS + ("debug_nan_at=35",), quiet=True)
    assert not os.path.exists(os.path.join(run, "model.pt"))
    with pytest.raises(UserError, match="no finished model"):
        load_run(run)
    state = torch.load(os.path.join(run, "checkpoints", "last.pt"), weights_only=True)
    assert state["iteration"] == 30
    assert all(torch.isfinite(v).all() for v in state["model"].values() if torch.is_tensor(v) and v.is_floating_point())
    # The CLI prints one line and exits non-zero.
    r = subprocess.run([sys.executable, "-m", "ctgs.cli", "train", scene, "-o", str(tmp_path / "nan2"),
                        "--preset", "fast", "-q"] + sum([["--set", s] for s in SETS + ("debug_nan_at=5",)], []),
                       cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 4 and "NaN/Inf in loss at iteration 5" in r.stderr and "Traceback" not in r.stderr


def test_parameter_inf_is_caught(scene, tmp_path):
    with pytest.raises(TrainingDiverged, match="parameter opacity_logits"):
        train_main(scene, str(tmp_path / "inf"), preset="fast", sets=SETS + ("lr_opacity=1e39",), quiet=True)


def _train_then_terminate(scene, run, ready, sets=()):
    """`ctgs train` in a subprocess, SIGTERM once `ready(run)` holds; returns the finished CompletedProcess-like."""
    args = [sys.executable, "-m", "ctgs.cli", "train", scene, "-o", run, "--preset", "fast", "-q"]
    for s in SETS + tuple(sets):
        args += ["--set", s]
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not ready(run) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    return proc.returncode, err


def test_sigterm_stops_training_like_ctrl_c_and_leaves_a_resumable_run(scene, tmp_path):
    """kill / timeout / a cluster's time limit: no native stack trace (pycolmap's glog handler would print one and
    end the process before Python cleans up), exit 143 (128 + SIGTERM), the checkpoint kept and the resume command
    named."""
    run = str(tmp_path / "term")
    ckpt = os.path.join(run, "checkpoints", "last.pt")
    code, err = _train_then_terminate(scene, run, lambda r: os.path.exists(ckpt),
                                      sets=("iterations=100000", "checkpoint_every=10"))
    assert code == 143, err
    assert "stack trace" not in err and "Traceback" not in err and "Aborted at" not in err, err
    assert f"-o {run} --resume" in err
    assert os.path.exists(ckpt) and not os.path.exists(os.path.join(run, "model.pt"))


def test_sigterm_before_the_first_checkpoint_removes_the_run_folder(scene, tmp_path, monkeypatch, capsys):
    """A stop before the first step: the folder this command made goes (nothing half-written stays)."""
    def stopped_at_once(self):
        raise Terminated(signal.SIGTERM)
        yield  # a generator, as Trainer.run

    monkeypatch.setattr(Trainer, "run", stopped_at_once)
    run = str(tmp_path / "term_early")
    with pytest.raises(Terminated):
        train_main(scene, run, preset="fast", sets=SETS, quiet=True)
    assert "stopped before the first checkpoint" in capsys.readouterr().err and not os.path.exists(run)


def test_sigterm_as_soon_as_the_run_folder_exists_leaves_no_folder_or_a_resumable_one(scene, tmp_path):
    """The same through a real signal, sent the moment the folder appears: wherever it lands (setup, or the first
    step, which then ends and is checkpointed), the folder is gone or holds a checkpoint `--resume` continues."""
    run = str(tmp_path / "term_early")
    code, err = _train_then_terminate(scene, run, os.path.isdir, sets=("iterations=100000",))
    assert code == 143 and "stack trace" not in err and "Traceback" not in err, err
    if "before the first checkpoint" in err:
        assert not os.path.exists(run)
    else:
        assert f"-o {run} --resume" in err and os.path.exists(os.path.join(run, "checkpoints", "last.pt")), err
        assert not os.path.exists(os.path.join(run, "model.pt"))


def _logged_steps(run: str) -> int:
    path = os.path.join(run, "log.jsonl")
    if not os.path.exists(path):
        return 0
    with open(path) as f:
        return sum(1 for line in f if '"type": "step"' in line)


def test_sigterm_mid_run_checkpoints_the_last_whole_step(scene, tmp_path):
    """A cluster's time limit or a preemption (SIGTERM) between periodic checkpoints: the step under way ends, a
    checkpoint of that state is written, and --resume continues from there (no step lost, none done twice)."""
    import torch

    run = str(tmp_path / "term_mid")
    code, err = _train_then_terminate(scene, run, lambda r: _logged_steps(r) >= 8,
                                      sets=("iterations=100000", "checkpoint_every=100000"))
    assert code == 143 and "Traceback" not in err, err
    state = torch.load(os.path.join(run, "checkpoints", "last.pt"), map_location="cpu", weights_only=True)
    assert state["iteration"] >= 8, state["iteration"]  # no periodic checkpoint was due: this is the stop's
    assert state["iteration"] >= _logged_steps(run)  # the step under way finished before it was written
    from ctgs.runs import training_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.loop.trainer import Trainer

    cfg = resolve_config(scene, run, None, None, (), None, True, None, None)  # the run's own config, as --resume
    assert Trainer(cfg, training_scene(cfg), run, resume=True).it == state["iteration"]
