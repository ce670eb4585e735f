"""One writer per run folder (ctgs.io.lock): while a training runs, a second `ctgs train` into its folder, a
`--resume` of it and a stage writing into it are refused with the holder's pid and host; once it is gone, however it
went (kill -9), nothing is blocked."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from fault_helpers import TRAIN_OPTS, assert_one_line_failure, cli

from ctgs.errors import UserError
from ctgs.io import lock


def _training(scene: str, run: str) -> subprocess.Popen:
    """A training long enough to be caught running, checkpointing every few steps."""
    opts = [o if o != "30" else "3000" for o in TRAIN_OPTS]
    return subprocess.Popen([sys.executable, "-m", "ctgs", "train", scene, "-o", run, *opts],
                            env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)


def _wait_for(path: str, proc: subprocess.Popen, timeout: float = 240.0) -> None:
    end = time.monotonic() + timeout
    while not os.path.isfile(path):
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < end, f"{path} never appeared"
        time.sleep(0.2)


def test_a_running_training_is_its_folders_only_writer(pipeline, tmp_path):
    run = str(tmp_path / "run")
    first = _training(pipeline["scene"], run)
    try:
        _wait_for(os.path.join(run, "checkpoints", "last.pt"), first)
        holder = (f"in use by `ctgs train` (pid {first.pid} on {socket.gethostname()}", "wait for it to end")
        for extra in ([], ["--resume"]):  # a second training with another seed, and a resume of this one
            line = assert_one_line_failure(cli(["train", pipeline["scene"], "-o", run, *TRAIN_OPTS, "--seed", "2",
                                                *extra]), codes=(2,), needles=holder)
            assert run in line
        # a stage writing into the run folder: an export of another run's model into it
        assert_one_line_failure(cli(["export", pipeline["run"], "--format", "ply", "-o", f"{run}/other.ply"]),
                                codes=(2,), needles=holder)
        assert not os.path.exists(f"{run}/other.ply")
        with open(os.path.join(run, "config.toml")) as fh:
            assert "seed = 0" in fh.read()  # the first training's config, not the refused one's
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    # the kernel released the dead process's lock: its record is left, and blocks no `--resume` (the crash
    # consistency check resumes after 20 such kills: test_interruptions.py)
    assert str(first.pid) in open(os.path.join(run, lock.LOCK_NAME)).read()
    held = lock.RunLock(run, "ctgs train")
    held.release()
    assert open(os.path.join(run, lock.LOCK_NAME)).read() == ""


def test_readers_share_and_exclude_the_writer(tmp_path):
    run = str(tmp_path / "run")
    writer = lock.RunLock(run, "ctgs train")
    with pytest.raises(UserError, match=f"pid {os.getpid()} "), lock.inside_run(os.path.join(run, "eval")):
        pass
    writer.release()
    with lock.inside_run(os.path.join(run, "eval")), lock.inside_run(os.path.join(run, "model")):
        # two stages at once; a training is refused (the last one's record was cleared: no stale pid is named)
        with pytest.raises(UserError, match="in use by another ctgs command"):
            lock.RunLock(run, "ctgs train")
    # a folder that is not a run folder (no lock file) takes no lock
    with lock.inside_run(str(tmp_path / "elsewhere" / "out")):
        assert not os.path.exists(tmp_path / "elsewhere")
