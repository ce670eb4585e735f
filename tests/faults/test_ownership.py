"""Every stage writes only into a folder it made or marked as its own (ctgs.io.owner): pointed at a folder of the
user's files, each refuses with one line and leaves every file as it was; its own earlier output it replaces."""

from __future__ import annotations

import hashlib
import os
import shutil

import pytest

from fault_helpers import (SCENE_OPTS, STAGES, assert_one_line_failure, cli, stage_commands, temporaries,
                           tiny_manifest)

from ctgs.io import owner

# every stage's output as a folder of the user's (the file formats' too: a folder where a file would go), and the
# stages' second forms: `--force` (sfm, demo-scene), `eval --table`, `fetch`
CASES = STAGES + ["sfm-force", "demo-scene-force", "eval-table", "fetch"]


def _users_folder(folder: str, photos: str) -> dict[str, str]:
    """A folder of the user's: photos (images/ too, the name a scene's folder has), a note. Returns its contents."""
    os.makedirs(os.path.join(folder, "images"), exist_ok=True)
    for i, name in enumerate(sorted(os.listdir(photos))[:3]):
        shutil.copy(os.path.join(photos, name), os.path.join(folder, f"IMG_{i:04d}.png"))
        shutil.copy(os.path.join(photos, name), os.path.join(folder, "images", f"IMG_{i:04d}.png"))
    with open(os.path.join(folder, "notes.txt"), "w") as fh:
        fh.write("the user's own\n")
    return _contents(folder)


def _contents(folder: str) -> dict[str, str]:
    out = {}
    for root, _dirs, files in os.walk(folder):
        for name in files:
            path = os.path.join(root, name)
            with open(path, "rb") as fh:
                out[os.path.relpath(path, folder)] = hashlib.sha256(fh.read()).hexdigest()
    return out


def _case(case: str, pipeline: dict, dest: str, monkeypatch) -> tuple[list[str], str]:
    if case == "eval-table":
        return ["eval", "--table", pipeline["run"], "-o", f"{dest}/table"], f"{dest}/table"
    if case == "fetch":  # refused before anything is downloaded
        monkeypatch.setenv("CTGS_MANIFEST_DIR", tiny_manifest(os.path.join(dest, "manifests")))
        return ["fetch", "tinyset", "tiny", "--root", f"{dest}/data"], f"{dest}/data/tinyset/tiny"
    stage, force = case.removesuffix("-force"), case.endswith("-force")
    args, out = stage_commands(pipeline, dest)[stage]
    return args + (["--force"] if force else []), out


@pytest.mark.parametrize("case", CASES)
def test_a_folder_of_the_users_files_is_refused_and_left_as_it_was(case, pipeline, tmp_path, monkeypatch):
    dest = str(tmp_path)
    args, out = _case(case, pipeline, dest, monkeypatch)
    mine = _users_folder(out, pipeline["photos"])
    line = assert_one_line_failure(cli(args), codes=(2,), needles=(out,))
    assert _contents(out) == mine, line  # nothing deleted, replaced or added
    assert temporaries(dest) == []


def test_render_into_the_users_photos_then_into_its_own_folder(pipeline, tmp_path):
    """The reproduction: `mkdir p; cp scene/images/00[3-7].png p; ctgs render RUN -o p` replaced the photos."""
    photos = tmp_path / "p"
    photos.mkdir()
    for name in sorted(os.listdir(f"{pipeline['scene']}/images"))[3:8]:
        shutil.copy(f"{pipeline['scene']}/images/{name}", photos / name)
    mine = _contents(str(photos))
    assert_one_line_failure(cli(["render", pipeline["run"], "-o", str(photos)]), codes=(2,),
                            needles=("not an earlier `ctgs render` folder",))
    assert _contents(str(photos)) == mine
    out = str(tmp_path / "renders")
    for _ in range(2):  # its own folder: replaced whole
        assert cli(["render", pipeline["run"], "-o", out]).exit_code == 0
    assert owner.kind_of(out) == "render"
    with open(os.path.join(out, "mine.txt"), "w") as fh:  # a file of the user's put into it since
        fh.write("keep\n")
    assert_one_line_failure(cli(["render", pipeline["run"], "-o", out]), codes=(2,), needles=("mine.txt",))
    assert os.path.isfile(os.path.join(out, "mine.txt"))


def test_outputs_from_before_markers_are_still_replaced(pipeline, tmp_path):
    """An eval folder, a model folder and a demo scene written before folders were marked: their names only, so
    they are ctgs's and replaced as before; one extra file of the user's makes each the user's."""
    for stage in ("eval", "export", "demo-scene"):
        args, out = stage_commands(pipeline, str(tmp_path))[stage]
        assert cli(args).exit_code == 0
        os.remove(os.path.join(out, owner.MARKER))
        if stage == "demo-scene":
            args = args + ["--force"]
        assert cli(args).exit_code == 0, stage
        os.remove(os.path.join(out, owner.MARKER))
        with open(os.path.join(out, "notes.txt"), "w") as fh:
            fh.write("mine\n")
        assert_one_line_failure(cli(args), codes=(2,), needles=("notes.txt",))


def test_a_run_folder_a_slurm_job_made_is_trained_into(pipeline, tmp_path):
    """A job script makes RUN and its slurm.log before `ctgs train`: that folder is a run folder."""
    args, out = stage_commands(pipeline, str(tmp_path))["train"]
    os.makedirs(out)
    with open(os.path.join(out, "slurm.log"), "w") as fh:
        fh.write("== ctgs slurm: scene tiny\n")
    assert cli(args).exit_code == 0
    assert owner.kind_of(out) == "run" and os.path.isfile(os.path.join(out, "model.pt"))


def test_sfm_force_replaces_only_its_own_entries(pipeline, tmp_path):
    """A 3DGS layout (the photos in SCENE/input): sfm adds its entries beside them, and --force replaces those, never
    the photos; a scene from before markers (its report) is sfm's too."""
    scene = tmp_path / "scene"
    shutil.copytree(pipeline["photos"], scene / "input")
    photos = _contents(str(scene / "input"))
    args = ["sfm", str(scene / "input"), "-o", str(scene), "--threads", "1"]
    assert cli(args).exit_code == 0
    assert owner.read_marker(str(scene)) == {"kind": "scene", "entries": ["images", "images_2", "images_4", "images_8",
                                                                           "sfm_report.json", "sparse"]}
    os.remove(scene / owner.MARKER)
    assert cli(args + ["--force"]).exit_code == 0
    assert _contents(str(scene / "input")) == photos
    assert os.path.isfile(scene / "sfm_report.json")


def test_demo_scene_force_replaces_an_earlier_demo_scene(tmp_path):
    out = str(tmp_path / "scene")
    assert cli(["demo-scene", out, *SCENE_OPTS]).exit_code == 0
    other = [o if o != "10" else "9" for o in SCENE_OPTS]  # --views 9: another demo scene
    assert_one_line_failure(cli(["demo-scene", out, *other]), codes=(2,), needles=("made with other options",))
    assert cli(["demo-scene", out, *other, "--force"]).exit_code == 0
    assert len(os.listdir(os.path.join(out, "images"))) == 9
