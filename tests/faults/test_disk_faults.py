"""Faults of the machine at every stage that writes: a full disk (a real small filesystem filled to several points,
and an ENOSPC injected at each atomic write) and a read-only output folder. Each case: one line naming the path and
the fix, exit 74, nothing half-written under a final name, no temporary left.

The small filesystem is a tmpfs (root only, as on the CI machine); the injected cases run everywhere.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from contextlib import contextmanager

import pytest

from ctgs.errors import OS_ERROR_EXIT
from fault_helpers import (STAGES, assert_nothing_half_written, assert_one_line_failure, can_mount, cli,
                           ctgs_subprocess, fill, inject_enospc, small_fs, stage_commands)

MOUNT = can_mount()
needs_mount = pytest.mark.skipif(not MOUNT, reason="mounting a tmpfs needs root (the injected cases still run)")
# How much room the disk has left, as a fraction of what the stage writes: nothing, and two points part-way.
ROOM = (0.0, 0.35, 0.7)


def _used(folder: str) -> int:
    st = os.statvfs(folder)
    return (st.f_blocks - st.f_bfree) * st.f_frsize


def _clear(folder: str) -> None:
    for name in os.listdir(folder):
        path = os.path.join(folder, name)
        shutil.rmtree(path) if os.path.isdir(path) and not os.path.islink(path) else os.remove(path)


@needs_mount
@pytest.mark.parametrize("stage", STAGES)
def test_full_disk(stage, pipeline):
    # sfm first checks that its disk holds its estimate (~20 MB here): a fuller disk is refused before it starts
    with small_fs(65536 if stage == "sfm" else 4096) as fs:
        args, out = stage_commands(pipeline, fs)[stage]
        before = _used(fs)
        result = cli(args)
        assert result.exit_code == 0, result.stderr
        need = _used(fs) - before  # what the stage writes, at least
        _clear(fs)
        for room in ROOM:
            filler = fill(fs, int(room * need))
            codes = (2, OS_ERROR_EXIT) if stage == "sfm" else (OS_ERROR_EXIT,)  # sfm's own check: a UserError
            line = assert_one_line_failure(cli(args), codes=codes, needles=("free space",))
            assert fs in line, line  # names the file on the full disk
            os.remove(filler)
            assert_nothing_half_written(stage, out, fs)
            _clear(fs)


@contextmanager
def _read_only(folder: str):
    """`folder` read-only as the kernel enforces it even for root: a read-only mount, else (not root) mode 0555."""
    if MOUNT:
        with small_fs(256) as fs:
            subprocess.run(["mount", "-o", "remount,ro", fs], check=True)
            try:
                yield fs
            finally:
                subprocess.run(["mount", "-o", "remount,rw", fs], check=True)
        return
    os.makedirs(folder)
    os.chmod(folder, 0o555)
    try:
        yield folder
    finally:
        os.chmod(folder, 0o755)


@pytest.mark.parametrize("stage", STAGES)
def test_read_only_output_folder(stage, pipeline, tmp_path):
    if os.geteuid() == 0 and not MOUNT:
        pytest.skip("root ignores folder modes and cannot mount here")
    with _read_only(str(tmp_path / "ro")) as ro:
        args, out = stage_commands(pipeline, ro)[stage]
        line = assert_one_line_failure(cli(args), codes=(OS_ERROR_EXIT,))
        assert ro in line and ("read-only" in line or "permission denied" in line), line
        assert os.listdir(ro) == []


@pytest.mark.parametrize("stage", STAGES)
def test_enospc_injected_at_each_write(stage, pipeline, tmp_path, monkeypatch):
    with monkeypatch.context() as m:
        calls = inject_enospc(m, None)
        assert cli(stage_commands(pipeline, str(tmp_path / "count"))[stage][0]).exit_code == 0
    total = calls[0]
    assert total >= 1
    # the first, a middle and the last write (every one would make the suite slow: render writes one per view)
    for k in sorted({1, (total + 1) // 2, total}):
        dest = str(tmp_path / f"write{k}")
        os.makedirs(dest)
        args, out = stage_commands(pipeline, dest)[stage]
        with monkeypatch.context() as m:
            inject_enospc(m, k)
            line = assert_one_line_failure(cli(args), codes=(OS_ERROR_EXIT,), needles=("no space left",))
        assert dest in line, line
        assert_nothing_half_written(stage, out, dest)


@needs_mount
@pytest.mark.parametrize("stage", ["render", "train", "export-spz"])
def test_full_disk_in_a_real_process_prints_one_line(stage, pipeline):
    # The in-process cases cannot see what C libraries print on file descriptor 2 (libpng, torch's zip writer):
    # a real `ctgs` process on a full disk, its whole stderr.
    with small_fs(4096) as fs:
        args, out = stage_commands(pipeline, fs)[stage]
        filler = fill(fs, 0)
        done = ctgs_subprocess(args)
        os.remove(filler)
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        assert done.returncode == OS_ERROR_EXIT and len(lines) == 1, (done.returncode, done.stderr[-2000:])
        assert lines[0].startswith(f"error: {fs}") and "no space left on the device" in lines[0], lines
        assert_nothing_half_written(stage, out, fs)
