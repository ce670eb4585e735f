"""Shared pieces of the fault-injection suite (tests/faults): the tiny pipeline every case starts from, the stage
commands, a small filesystem that can be filled or made read-only, and the one assertion every case makes.

The contract each case checks (the project's rule for bad input and faults of the machine): the command exits
non-zero with exactly one line on stderr, `error: ...`, naming the file; and nothing half-written stands under a
final name (the output is absent or whole, and no temporary is left).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import subprocess
import sys
import tempfile
import warnings

from click.testing import CliRunner

from ctgs.cli import main
from ctgs.errors import OS_ERROR_EXIT
from ctgs.io import atomic

TEMP = re.compile(r"\.tmp-")  # the atomic helpers' temporaries (ctgs.io.atomic)
# sfm's work folder: kept on a failure (the same command resumes from it), gone after a successful run
SFM_WORK = re.compile(r"\.sfm-work$")
# The tiny pipeline: a 64x48 demo scene of 10 views, 30 iterations of the fast preset (a few seconds).
SCENE_OPTS = ["--views", "10", "--width", "64", "--height", "48", "--points", "600", "--supersample", "1"]
# export --format -> file ending, of the files for Gaussian viewers
GAUSSIAN_FILES = {"ply": "ply", "splat": "splat", "spz": "spz", "compressed-ply": "compressed.ply", "sog": "sog",
                  "glb-splats": "splats.glb"}
TRAIN_OPTS = ["--preset", "fast", "--iterations", "30", "-q", "--set", "threads=1", "--set", "checkpoint_every=10",
              "--backend", "cpu"]


def stage_commands(p: dict, dest: str) -> dict[str, tuple[list[str], str]]:
    """Every stage that writes, as (ctgs arguments, its output path), reading the pipeline `p` and writing
    under `dest`."""
    return {
        "sfm": (["sfm", p["photos"], "-o", f"{dest}/sfmscene", "--threads", "1"], f"{dest}/sfmscene"),
        "demo-scene": (["demo-scene", f"{dest}/scene", *SCENE_OPTS], f"{dest}/scene"),
        "train": (["train", p["scene"], "-o", f"{dest}/run", *TRAIN_OPTS], f"{dest}/run"),
        "export": (["export", p["run"], "-o", f"{dest}/model"], f"{dest}/model"),
        "export-ply": (["export", p["run"], "--format", "ply", "-o", f"{dest}/m.ply"], f"{dest}/m.ply"),
        "export-splat": (["export", p["run"], "--format", "splat", "-o", f"{dest}/m.splat"], f"{dest}/m.splat"),
        "export-spz": (["export", p["run"], "--format", "spz", "-o", f"{dest}/m.spz"], f"{dest}/m.spz"),
        "export-glb": (["export", p["run"], "--format", "glb", "-o", f"{dest}/m.glb"], f"{dest}/m.glb"),
        "export-web": (["export", p["run"], "--format", "web", "-o", f"{dest}/web"], f"{dest}/web"),
        "export-compressed-ply": (["export", p["run"], "--format", "compressed-ply", "-o", f"{dest}/m.compressed.ply"],
                                  f"{dest}/m.compressed.ply"),
        "export-sog": (["export", p["run"], "--format", "sog", "-o", f"{dest}/m.sog"], f"{dest}/m.sog"),
        "export-glb-splats": (["export", p["run"], "--format", "glb-splats", "-o", f"{dest}/m.splats.glb"],
                              f"{dest}/m.splats.glb"),
        "compress": (["compress", p["model"], "-o", f"{dest}/small"], f"{dest}/small"),
        "eval": (["eval", p["run"], "--no-lpips", "-o", f"{dest}/eval"], f"{dest}/eval"),
        "render": (["render", p["run"], "-o", f"{dest}/render"], f"{dest}/render"),
    }


STAGES = list(stage_commands({k: "" for k in ("photos", "scene", "run", "model")}, "").keys())


def tiny_manifest(folder: str, scene: str = "tiny") -> str:
    """A dataset manifest, `tinyset`, listing `scene` (its archive is never downloaded) in `folder` (made): the folder
    for CTGS_MANIFEST_DIR."""
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "tinyset.toml"), "w") as fh:
        fh.write('name = "tinyset"\nholdout = 4\nimages = "images"\n\n[archives.none]\n'
                 f'url = "http://127.0.0.1:9/none.zip"\n\n[scenes.{scene}]\narchive = "none"\n')
    return folder


def cli(args: list[str]):
    """`ctgs ARGS` in this process (CliRunner: stderr apart from stdout). Python warnings, which a real run prints
    on stderr and CliRunner does not capture, are added to `result.warnings` as the lines they would print."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.resetwarnings()  # Python's own defaults, as a user's run has them (not pytest's)
        warnings.simplefilter("default")
        for quiet in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
            warnings.simplefilter("ignore", quiet)
        result = CliRunner().invoke(main, args)
    result.warnings = [f"{w.category.__name__}: {w.message}" for w in caught]
    return result


def assert_one_line_failure(result, codes=(2, OS_ERROR_EXIT), needles=()) -> str:
    """Non-zero exit (one of `codes`), no traceback, exactly one stderr line `error: ...` holding every needle."""
    assert not (result.exception and not isinstance(result.exception, SystemExit)), (
        f"uncaught {type(result.exception).__name__}: {result.exception}\n{result.stderr}")
    lines = [line for line in result.stderr.splitlines() if line.strip()] + getattr(result, "warnings", [])
    assert result.exit_code in codes, (result.exit_code, result.stderr)
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    assert not TEMP.search(lines[0]), f"names a hidden temporary, not the file the user asked for: {lines[0]}"
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def temporaries(root: str, *, work: bool = True) -> list[str]:
    """Every temporary left anywhere under `root` (work: sfm's work folder counts as one)."""
    found = []
    for folder, dirs, files in os.walk(root):
        found += [os.path.join(folder, n) for n in dirs + files
                  if TEMP.search(n) or (work and SFM_WORK.search(n))]
    return found


def assert_nothing_half_written(stage: str, out: str, root: str) -> None:
    """No temporary under `root`, and `out` absent, or (train) a run folder a checkpoint made resumable and
    without a finished model."""
    assert temporaries(root, work=False) == [], temporaries(root, work=False)
    if stage == "train" and os.path.exists(out):
        names = set(os.listdir(out))
        ckpts = os.listdir(os.path.join(out, "checkpoints")) if "checkpoints" in names else []
        assert "model.pt" not in names and "train_summary.json" not in names, names
        assert {"last.pt", "prev.pt"} & set(ckpts), f"a run folder without a checkpoint was left: {names} {ckpts}"
        return
    assert not os.path.lexists(out), f"{out} stands after the failure: {os.listdir(out) if os.path.isdir(out) else ''}"


def can_mount() -> bool:
    if os.geteuid() != 0 or not shutil.which("mount"):
        return False
    probe = tempfile.mkdtemp(prefix="ctgs-mount-probe-")
    try:
        if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", probe], capture_output=True).returncode:
            return False
        subprocess.run(["umount", probe], capture_output=True)
        return True
    finally:
        os.rmdir(probe)


@contextlib.contextmanager
def small_fs(size_kib: int):
    """A tmpfs of size_kib (root only): a disk that really fills up, for OpenImageIO's and torch's own writes too."""
    where = tempfile.mkdtemp(prefix="ctgs-small-fs-")
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k,mode=0755", "tmpfs", where], check=True)
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", where], check=True)
        os.rmdir(where)


def fill(folder: str, leave_bytes: int) -> str:
    """Fill the filesystem of `folder` until about `leave_bytes` are free; returns the filler's path."""
    path = os.path.join(folder, "filler")
    st = os.statvfs(folder)
    free = st.f_bavail * st.f_frsize
    with open(path, "wb") as f:
        f.write(b"\0" * max(0, free - leave_bytes))
    return path


def ctgs_subprocess(args: list[str], *, kill_at_write: int | None = None,
                    timeout: float = 300.0) -> subprocess.CompletedProcess:
    """`ctgs ARGS` in a child process. kill_at_write=N: the child SIGKILLs itself while the N-th atomic write's
    temporary is complete but not yet renamed (the worst moment)."""
    hook = os.path.join(os.path.dirname(os.path.abspath(__file__)), "kill_hook.py")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CTGS_KILL_AT_WRITE": str(kill_at_write or 0)}
    return subprocess.run([sys.executable, hook, *args], env=env, capture_output=True, text=True, timeout=timeout)


def inject_enospc(monkeypatch, fail_at: int | None) -> list[int]:
    """Count the atomic writes; fail_at=N: the N-th raises ENOSPC once its temporary is written, as a write on a
    full disk does (an OSError naming no file)."""
    calls = [0]

    def wrap(original):
        @contextlib.contextmanager
        def wrapped(*args, **kwargs):
            calls[0] += 1
            n = calls[0]
            with original(*args, **kwargs) as tmp:
                yield tmp
                if n == fail_at:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        return wrapped

    monkeypatch.setattr(atomic, "atomic_path", wrap(atomic.atomic_path))
    monkeypatch.setattr(atomic, "atomic_dir", wrap(atomic.atomic_dir))
    return calls
