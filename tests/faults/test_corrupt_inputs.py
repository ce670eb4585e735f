"""Every file a stage reads, cut in half, emptied, or replaced by random bytes of the same length: the stage exits
2 (or 74) with one line naming that file, and writes nothing. Resuming from a damaged checkpoint falls back to the
one before it, and says so."""

from __future__ import annotations

import contextlib
import os
import random
import shutil

import pytest
import torch

from fault_helpers import GAUSSIAN_FILES, SCENE_OPTS, TRAIN_OPTS, assert_nothing_half_written, assert_one_line_failure, cli

VARIANTS = ("cut", "empty", "random")
SPARSE = "scene/sparse/0/"


def _commands(p: dict, dest: str) -> dict[str, list[str]]:
    return {
        "sfm": ["sfm", p["photos"], "-o", f"{dest}/out", "--threads", "1"],
        "demo-scene": ["demo-scene", p["scene"], *SCENE_OPTS],  # the same scene again: checked by its record
        "train": ["train", p["scene"], "-o", f"{dest}/out", *TRAIN_OPTS],
        "train-text": ["train", p["textscene"], "-o", f"{dest}/out", *TRAIN_OPTS],
        "export": ["export", p["run"], "-o", f"{dest}/out"],
        "export-web": ["export", p["run"], "--format", "web", "-o", f"{dest}/out"],
        "compress": ["compress", p["model"], "-o", f"{dest}/out"],
        "eval": ["eval", p["run"], "--no-lpips", "-o", f"{dest}/out"],
        "eval-table": ["eval", p["run"], "--table", "-o", f"{dest}/out"],
        "eval-compressed": ["eval", p["run"], "--model", p["small"], "--no-lpips", "-o", f"{dest}/out"],
        "render": ["render", p["run"], "-o", f"{dest}/out"],
        "render-model": ["render", p["run"], "--model", p["model"], "-o", f"{dest}/out"],
        **{f"eval-{ext}": ["eval", p["run"], "--model", f"{p['root']}/run/m.{ext}", "--no-lpips", "-o", f"{dest}/out"]
           for ext in GAUSSIAN_FILES.values()},
        "view": ["view", p["web"], "--no-browser", "--port", "0"],
        "view-model": ["view", p["model"], "--no-browser", "--port", "0"],
    }


# (stage, file under the pipeline's root that it reads)
CASES = [
    ("sfm", "photos/images/005.png"),
    ("demo-scene", "scene/demo_meta.json"),
    *[("train", SPARSE + f"{name}.bin") for name in ("cameras", "images", "points3D", "frames", "rigs")],
    ("train", "scene/images/003.png"),
    *[("train-text", f"textscene/sparse/0/{name}.txt") for name in ("cameras", "images", "points3D", "frames", "rigs")],
    ("export", "run/model.pt"),
    ("export-web", SPARSE + "cameras.bin"),
    ("compress", "run/model/manifest.json"),
    ("compress", "run/model/primitives.ply"),
    ("compress", "run/model/textures.bin"),
    ("eval", "run/model.pt"),
    ("eval", "run/train_summary.json"),
    ("eval", "scene/images/000.png"),
    ("eval", SPARSE + "images.bin"),
    ("eval-table", "run/eval/metrics.json"),
    ("eval-compressed", "run/small/manifest.json"),
    ("eval-compressed", "run/small/model.bin"),
    ("render", "run/model.pt"),
    ("render", SPARSE + "points3D.bin"),
    ("render-model", "run/model/primitives.ply"),
    ("render-model", "run/model/textures.bin"),
    *[(f"eval-{ext}", f"run/m.{ext}") for ext in GAUSSIAN_FILES.values()],
    ("view", "run/webmodel/web/bundle.json"),
    ("view", "run/webmodel/web/surfels.bin"),
    ("view", "run/webmodel/web/atlas_000.bin"),
    ("view-model", "run/model/primitives.ply"),
]
# Random bytes of the right length in the bundle's data arrays are values like any others: no reader can tell.
UNCHECKABLE = {("view", "run/webmodel/web/surfels.bin", "random"), ("view", "run/webmodel/web/atlas_000.bin", "random")}


def _damage(data: bytes, variant: str, seed: int) -> bytes:
    if variant == "cut":  # (one byte short of half: a .splat cut on a record boundary is a smaller valid .splat)
        return data[: max(0, len(data) // 2 - 1)]
    if variant.startswith("cut:"):  # cut to so many bytes
        return data[: int(variant[4:])]
    if variant == "empty":
        return b""
    return random.Random(seed).randbytes(len(data))


@contextlib.contextmanager
def damaged(path: str, variant: str, seed: int = 0):
    """`path` damaged for the block, restored after."""
    with open(path, "rb") as f:
        original = f.read()
    try:
        with open(path, "wb") as f:
            f.write(_damage(original, variant, seed))
        yield
    finally:
        with open(path, "wb") as f:
            f.write(original)


DAMAGED = [(stage, rel, v) for stage, rel in CASES for v in VARIANTS if (stage, rel, v) not in UNCHECKABLE]


@pytest.mark.parametrize(("stage", "rel", "variant"), DAMAGED,
                         ids=[f"{s}-{os.path.basename(r)}-{v}" for s, r, v in DAMAGED])
def test_damaged_input_is_named(stage, rel, variant, pipeline, tmp_path, monkeypatch):
    from ctgs.viewer.server import ViewerServer

    def serve_forever(self):
        raise AssertionError("`ctgs view` served a damaged bundle")

    monkeypatch.setattr(ViewerServer, "serve_forever", serve_forever)
    dest = str(tmp_path)
    path = os.path.join(pipeline["root"], rel)
    with damaged(path, variant, seed=len(rel)):
        result = cli(_commands(pipeline, dest)[stage])
    assert_one_line_failure(result, needles=(os.path.basename(rel),))
    assert_nothing_half_written(stage, f"{dest}/out", dest)


def _stopped_run(pipeline: dict, where: str) -> str:
    """A copy of the pipeline's run as a kill would leave it: checkpoints (last.pt at iteration 30, prev.pt at 20)
    and no finished model."""
    run = shutil.copytree(pipeline["run"], where, ignore=shutil.ignore_patterns("model", "small"))
    for name in ("model.pt", "train_summary.json"):
        os.remove(os.path.join(run, name))
    return run


@pytest.mark.parametrize("variant", VARIANTS)
def test_resume_falls_back_to_the_previous_checkpoint(variant, pipeline, tmp_path):
    run = _stopped_run(pipeline, str(tmp_path / "run"))
    last = os.path.join(run, "checkpoints", "last.pt")
    with open(last, "rb") as f:
        data = f.read()
    with open(last, "wb") as f:
        f.write(_damage(data, variant, 1))
    result = cli(["train", pipeline["scene"], "-o", run, *TRAIN_OPTS, "--resume"])
    assert result.exit_code == 0, result.stderr
    note = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(note) == 1 and "last.pt unreadable" in note[0] and "prev.pt" in note[0], result.stderr
    assert os.path.isfile(os.path.join(run, "model.pt"))


def test_resume_with_a_damaged_config_or_log(pipeline, tmp_path):
    run = _stopped_run(pipeline, str(tmp_path / "run"))
    config = os.path.join(run, "config.toml")
    with damaged(config, "random"):
        result = cli(["train", pipeline["scene"], "-o", run, "--resume", "-q"])
        assert_one_line_failure(result, codes=(2,), needles=("config.toml", "invalid TOML"))
    with damaged(os.path.join(run, "log.jsonl"), "random"):  # the log is a record: its unreadable lines go
        result = cli(["train", pipeline["scene"], "-o", run, "--resume", "-q"])
        assert result.exit_code == 0, result.stderr
    assert os.path.isfile(os.path.join(run, "model.pt"))


def test_resume_with_no_readable_checkpoint_is_one_line(pipeline, tmp_path):
    run = _stopped_run(pipeline, str(tmp_path / "run"))
    for name in ("last.pt", "prev.pt"):
        with open(os.path.join(run, "checkpoints", name), "r+b") as f:
            f.truncate(100)
    result = cli(["train", pipeline["scene"], "-o", run, *TRAIN_OPTS, "--resume"])
    line = assert_one_line_failure(result, codes=(2,), needles=("last.pt", "prev.pt", "without --resume"))
    assert "Traceback" not in line
    assert not os.path.exists(os.path.join(run, "model.pt"))


class _CreatesAFile:
    """Unpickled, creates `path`: a pickle may call any function it names, here `open`."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return open, (self.path, "w")


def test_resume_refuses_a_checkpoint_that_would_run_code(pipeline, tmp_path):
    """A run folder from someone else: its last.pt, unpickled, would create a file. --resume refuses it in one line,
    runs nothing of it, and does not quietly start from prev.pt instead (tests/runs/test_checkpoint_pickles.py)."""
    run = _stopped_run(pipeline, str(tmp_path / "run"))
    last = os.path.join(run, "checkpoints", "last.pt")
    state = torch.load(last, weights_only=True)
    control, marker = tmp_path / "control.pt", tmp_path / "ran"
    torch.save(state | {"rng": state["rng"] | {"extra": _CreatesAFile(str(tmp_path / "control_ran"))}}, control)
    torch.load(control, weights_only=False)  # the payload works: unpickled as-is, it creates its file
    assert (tmp_path / "control_ran").exists()
    torch.save(state | {"rng": state["rng"] | {"extra": _CreatesAFile(str(marker))}}, last)

    result = cli(["train", pipeline["scene"], "-o", run, *TRAIN_OPTS, "--resume"])
    assert_one_line_failure(result, codes=(2,), needles=("last.pt", "io.open", "nothing of it was run"))
    assert not marker.exists()
    assert not os.path.exists(os.path.join(run, "model.pt")) and os.path.exists(last)


def test_a_model_of_random_bytes_is_named(pipeline, tmp_path):
    # the issue's case: a model.pt of random bytes gave pickle.UnpicklingError's traceback
    run = shutil.copytree(pipeline["run"], str(tmp_path / "run"), ignore=shutil.ignore_patterns("model", "small"))
    with open(os.path.join(run, "model.pt"), "wb") as f:
        f.write(random.Random(5).randbytes(4096))
    assert_one_line_failure(cli(["export", run, "-o", str(tmp_path / "out")]), codes=(2,),
                            needles=("model.pt", "corrupt"))
    assert not os.path.exists(tmp_path / "out")


@pytest.mark.parametrize("size", [30, 10])
def test_cameras_bin_cut_to_the_issue_sizes_is_named_at_load(size, pipeline, tmp_path):
    # cut to 30 bytes it once passed the scene checks and training died 19 s later in the renderer (fx = 0); cut
    # to 10, the message blamed the aspect ratio
    with damaged(os.path.join(pipeline["root"], SPARSE, "cameras.bin"), f"cut:{size}"):
        result = cli(_commands(pipeline, str(tmp_path))["train"])
    line = assert_one_line_failure(result, codes=(2,), needles=("cameras.bin", "corrupt COLMAP cameras file"))
    assert "aspect" not in line
    assert not os.path.exists(tmp_path / "out")
