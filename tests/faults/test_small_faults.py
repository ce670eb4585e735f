"""The smaller ways a user's run went wrong silently: a zero time budget, a model.pt from another run, a size budget
that cannot be met, sfm's damaged work files, the viewer's dropped clients, listings and links, and a Slurm sweep
naming a scene folder that is not there."""

from __future__ import annotations

import io
import os
import shutil
import socket
import sys
import urllib.error
import urllib.request
import uuid

import pytest
import torch

from fault_helpers import TRAIN_OPTS, assert_one_line_failure, cli, tiny_manifest

from ctgs.launch import slurm
from ctgs.scene.sfm import markers as sfm_markers
from ctgs.viewer.server import ViewerServer


def test_a_zero_time_budget_is_refused(pipeline, tmp_path):
    run = str(tmp_path / "run")
    assert_one_line_failure(cli(["train", pipeline["scene"], "-o", run, *TRAIN_OPTS, "--time-budget", "0"]),
                            codes=(2,), needles=("--time-budget 0", "minutes above 0"))
    assert not os.path.exists(run)


@pytest.fixture
def copied_run(pipeline, tmp_path) -> str:
    """The pipeline's run folder, its files only (not its exports)."""
    run = tmp_path / "run"
    run.mkdir()
    for name in ("model.pt", "train_summary.json", "config.toml"):
        shutil.copy(os.path.join(pipeline["run"], name), run / name)
    return str(run)


def _rewrite(path: str, **changes) -> None:
    state = torch.load(path, weights_only=True)
    state.update(changes)
    for key in [k for k, v in changes.items() if v is None]:
        del state[key]
    torch.save(state, path)


@pytest.mark.parametrize("stage", ["eval", "export", "render"])
def test_a_model_pt_from_another_run_is_refused(stage, copied_run, tmp_path):
    """model.pt copied in from another run (another model_id): its iterations and times are not the summary's."""
    _rewrite(os.path.join(copied_run, "model.pt"), model_id=uuid.uuid4().hex, iteration=12)
    args = {"eval": ["eval", copied_run, "--no-lpips"], "export": ["export", copied_run],
            "render": ["render", copied_run, "-o", str(tmp_path / "r")]}[stage]
    assert_one_line_failure(cli(args), codes=(2,), needles=(f"{copied_run}/model.pt: another run's model (iteration "
                                                            "12)", "train_summary.json"))


def test_runs_from_before_model_ids_are_matched_by_iteration(copied_run, tmp_path):
    import json

    path, spath = os.path.join(copied_run, "model.pt"), os.path.join(copied_run, "train_summary.json")
    summary = json.load(open(spath))
    del summary["model_id"]
    with open(spath, "w") as fh:
        json.dump(summary, fh)
    _rewrite(path, model_id=None)
    assert cli(["export", copied_run, "--format", "ply", "-o", str(tmp_path / "m.ply")]).exit_code == 0
    _rewrite(path, iteration=summary["iterations"] + 1)
    assert_one_line_failure(cli(["export", copied_run, "--format", "ply", "-o", str(tmp_path / "n.ply")]),
                            codes=(2,), needles=("another run's model",))


def test_a_size_budget_that_cannot_be_met_is_an_error(pipeline, tmp_path):
    run = str(tmp_path / "run")
    result = cli(["train", pipeline["scene"], "-o", run, *TRAIN_OPTS, "--max-params", "10"])
    line = assert_one_line_failure(result, codes=(3,), needles=(f"{run}/model.pt", "size budget 10 params: missed by"))
    assert "--max-params" in line and os.path.isfile(os.path.join(run, "model.pt"))  # the model is kept


def test_sfm_resumes_past_a_damaged_record_of_its_inputs(pipeline, tmp_path):
    out = tmp_path / "scene"
    work = tmp_path / ".scene.sfm-work"
    work.mkdir()
    (work / "inputs.json").write_text("[" * 100000)  # nested past Python's recursion limit
    result = cli(["sfm", pipeline["photos"], "-o", str(out), "--threads", "1"])
    assert result.exit_code == 0, result.stderr
    assert "inputs.json: unreadable (damaged); the SfM steps are redone" in result.stderr
    assert (out / "sfm_report.json").is_file() and not work.exists()


def test_a_folder_where_the_record_of_the_inputs_goes_is_damage_too(tmp_path, capsys):
    work = tmp_path / "work"
    (work / "inputs.json").mkdir(parents=True)
    fingerprint = {"images_dir": str(tmp_path), "files": [], "max_image_size": 0, "max_features": 0,
                   "matcher": "exhaustive", "mapper": "incremental"}
    sfm_markers.prepare_work(str(work), fingerprint, force=False)
    assert (work / "inputs.json").is_file() and "unreadable (damaged)" in capsys.readouterr().err


def test_a_damaged_step_marker_reads_as_unknown_figures(tmp_path):
    marker = tmp_path / "features.done"
    for text, figures in (("12.5 30.0\n", (12.5, 30.0)), ("12.5\n", (12.5, None)), ("\x00garbage", (None, None))):
        marker.write_text(text)
        got = sfm_markers.step_figures(str(marker))
        assert [None if g != g else g for g in got] == list(figures)  # NaN for what it no longer says


@pytest.fixture
def served(pipeline, tmp_path):
    bundle = shutil.copytree(pipeline["web"], tmp_path / "web")
    (tmp_path / "secret.txt").write_text("outside the bundle\n")
    os.symlink(tmp_path / "secret.txt", bundle / "leak.bin")
    with ViewerServer(str(bundle)) as server:
        yield server


def _get(server: ViewerServer, path: str) -> int:
    try:
        return urllib.request.urlopen(server.url.rstrip("/") + path, timeout=30).status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_the_viewer_lists_nothing_and_follows_no_link_out(served):
    assert _get(served, "/bundle/bundle.json") == 200 and _get(served, "/bundle/surfels.bin") == 200
    for path in ("/bundle/", "/bundle", "/bundle/leak.bin", "/bundle/.ctgs-output", "/bundle/..%2fsecret.txt"):
        assert _get(served, path) in (400, 404), path
    assert _get(served, "/") == 200  # the page itself


def test_the_viewer_is_quiet_about_clients_that_went_away(served, monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    for exc in (ConnectionResetError(104, "Connection reset by peer"), BrokenPipeError(32, "Broken pipe"),
                TimeoutError("timed out")):
        try:
            raise exc
        except OSError:
            served.httpd.handle_error(None, ("127.0.0.1", 1))
    assert err.getvalue() == ""
    for _ in range(20):  # real ones: ask for the largest file and reset the connection at once
        s = socket.create_connection(("127.0.0.1", served.port))
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        s.sendall(f"GET /bundle/surfels.bin HTTP/1.1\r\nHost: 127.0.0.1:{served.port}\r\n\r\n".encode())
        s.close()
    assert _get(served, "/bundle/bundle.json") == 200
    assert "Traceback" not in err.getvalue(), err.getvalue()
    try:
        raise ValueError("a bug of ours")
    except ValueError:
        served.httpd.handle_error(None, ("127.0.0.1", 1))
    assert "ValueError: a bug of ours" in err.getvalue()  # what is not a dropped client is still said


def test_slurm_submit_checks_scene_dir_folders(pipeline, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CTGS_MANIFEST_DIR", tiny_manifest(str(tmp_path / "m"), "tinya"))
    monkeypatch.setenv("PATH", str(tmp_path / "no-slurm-here"))
    base = ["submit", "--scenes", "tinya", "--runs", str(tmp_path / "runs"), "--root", str(tmp_path), "--"]
    assert slurm.main(base + ["SCENE_DIR_tinya=nowhere/tinya"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: SCENE_DIR_tinya=nowhere/tinya: no such folder") and len(err.splitlines()) == 1, err
    assert slurm.main(base + [f"SCENE_DIR_tinya={pipeline['scene']}"]) == 2  # the folder is there: on to sbatch
    assert "sbatch: not found" in capsys.readouterr().err
