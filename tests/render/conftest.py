"""The CUDA compile check of tests/render/test_cuda_backend.py (kernels/check_cuda_build.py: every kernels/cuda/*.cu
for two architectures, and the binding's host syntax against torch's headers) is a minute or two of nvcc and g++ on a
small machine, while the rest of the suite runs its trainings and renders on one core. So when that test is among the
tests to run and nvcc exists, the check starts in the background as soon as collection ends, on one core and at low
priority, and the test collects its output when its turn comes: the same compilation, the same assertions, off the
suite's critical path. Alone (`pytest -k nvcc`), the test waits for it as it would for any compile."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CHECK_TEST = "test_cuda_sources_compile_with_nvcc"
# Below the tests' own priority: on a machine with no spare core the check waits rather than slowing timed tests.
NICENESS = 10
_JOB = pytest.StashKey[tuple]()


def check_command(jobs: int | None = None) -> list[str]:
    return [sys.executable, str(ROOT / "kernels" / "check_cuda_build.py"), "--resources",
            *(["--jobs", str(jobs)] if jobs else [])]


def _lower_priority(nice: int) -> None:
    """In the check's process (a session of its own): its nice value, and its autogroup's where the kernel groups
    sessions (sched_autogroup): there a new session competes with the suite's as an equal whatever its nice value."""
    os.nice(nice)
    try:
        with open("/proc/self/autogroup", "w") as fh:
            fh.write(str(nice))
    except OSError:  # no autogroups (or not writable): the nice value alone
        pass


def _start(jobs: int | None, nice: int) -> tuple[subprocess.Popen, object, object]:
    out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
    proc = subprocess.Popen(check_command(jobs), stdout=out, stderr=err, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=True,
                            preexec_fn=(lambda: _lower_priority(nice)) if nice else None)
    return proc, out, err


@pytest.hookimpl(trylast=True)  # after -k / -m have deselected what they deselect
def pytest_collection_modifyitems(session, config, items):
    if config.option.collectonly or shutil.which("nvcc") is None:
        return
    if any(item.name == CHECK_TEST for item in items):
        alone = len(items) == 1  # nothing to share the machine with: every core, at the usual priority
        config.stash[_JOB] = _start(jobs=None, nice=0) if alone else _start(jobs=1, nice=NICENESS)


def pytest_unconfigure(config):
    job = config.stash.get(_JOB, None)
    if job is not None and job[0].poll() is None:  # the run ended first (-x, Ctrl-C): no compiler left behind
        os.killpg(job[0].pid, signal.SIGKILL)
        job[0].wait()


@pytest.fixture
def cuda_check(request) -> subprocess.CompletedProcess:
    """kernels/check_cuda_build.py --resources, finished: the background run's, else one run now (every core)."""
    job = request.config.stash.get(_JOB, None)
    proc, out, err = job if job is not None else _start(jobs=None, nice=0)
    proc.wait()
    out.seek(0)
    err.seek(0)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out.read(), err.read())
