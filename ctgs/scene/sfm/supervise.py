"""Worker supervision: each long pycolmap call runs in a child process (ctgs.scene.sfm.worker). COLMAP ends its process
with a native stack dump on a failed check (SQLite's "database or disk is full" among them); here that ends the
child, and `ctgs sfm` says what happened in one line (SfmStopped) and keeps the work folder to resume."""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable

from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.scene.sfm.progress import tail

# Below this much free space a failed COLMAP call is taken for a full disk.
LOW_SPACE_BYTES = 64 << 20


class SfmStopped(UserError):
    """A pycolmap step ended its process (a full disk, a failed COLMAP check): the work folder is kept, so that the
    same command resumes from the finished steps once the cause is fixed."""

    keep_work = True


def _die_with_parent() -> None:  # pragma: no cover (runs in the child between fork and exec)
    """The worker ends when `ctgs sfm` does (SIGTERM ends the parent at once, see run_sfm)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def worker_command(job_path: str) -> list[str]:
    return [sys.executable, "-m", "ctgs.scene.sfm.worker", job_path]


_CALL_NAMES = {"extract": "SIFT extraction", "match": "matching", "map_incremental": "incremental mapping",
               "map_global": "global mapping", "undistort": "undistortion"}


def _worker_failure(call: str, log: str, work: str, code: int) -> SfmStopped:
    step = _CALL_NAMES.get(call, call)
    text = tail(log)
    try:
        free = shutil.disk_usage(work).free
    except OSError:
        free = 0
    if "disk is full" in text or "No space left" in text or free < LOW_SPACE_BYTES:
        return SfmStopped(f"{work}: the disk is full ({free / 1e6:.0f} MB free) during {step}; free space on it "
                          f"and run the same command again: it resumes after the finished steps")
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    marks = ("Check failed", "FATAL", "Error", "error", "Exception", "exception")
    cause = next((line for line in reversed(lines) if any(m in line for m in marks)), lines[-1] if lines else "")
    cause = " ".join(cause.split())[-200:]
    how = f"signal {-code}" if code < 0 else f"exit {code}"
    return SfmStopped(f"{log}: COLMAP stopped during {step} ({how}: {cause or 'no message'}); see this log, fix "
                      f"the cause and run the same command again (it resumes after the finished steps)")


def run_worker(work: str, call: str, job: dict, poll: Callable[[], None] | None = None,
               verbose: bool = False) -> dict:
    """Run one pycolmap call in a child process (ctgs.scene.sfm.worker), calling `poll` twice a second; its
    result dict, or SfmStopped when the child failed (a native abort included)."""
    job = {**job, "call": call, "result": os.path.join(work, f"{call}.result.json"),
           "progress": os.path.join(work, f"{call}.progress.json"), "log_level": 0}
    for stale in (job["result"], job["progress"]):
        if os.path.exists(stale):
            os.remove(stale)
    job_path = os.path.join(work, f"{call}.job.json")
    atomic.write_json(job_path, job, indent=None)
    log = os.path.join(work, f"{call}.log")
    with open(log, "wb") as out:
        proc = subprocess.Popen(worker_command(job_path), stdin=subprocess.DEVNULL, stdout=None if verbose else out,
                                stderr=None if verbose else out, preexec_fn=_die_with_parent)
        try:
            while proc.poll() is None:
                if poll is not None:
                    poll()
                try:
                    proc.wait(0.5)
                except subprocess.TimeoutExpired:
                    pass
        except BaseException:
            proc.kill()
            proc.wait()
            raise
    if proc.returncode != 0 or not os.path.isfile(job["result"]):
        raise _worker_failure(call, log, work, proc.returncode)
    with open(job["result"]) as f:
        return json.load(f)
