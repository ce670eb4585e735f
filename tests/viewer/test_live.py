"""`ctgs view RUN_DIR` on a run folder being written (ctgs.viewer.live and its server routes), without a browser:
each newer whole checkpoint is shown once, a cut or hidden one never; the log is read a whole line at a time; only the
run folder's own files are read (no link out of it, no pickled code run); the server's checks hold for /live/."""

from __future__ import annotations

import json
import os
import shutil
import socket
import threading
import urllib.error
import urllib.request

import pytest
import torch
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.runs import checkpoint as ckpt
from ctgs.viewer.live import MAX_CURVE, LiveRun, is_run_folder
from ctgs.viewer.server import CSP, ViewerServer
from viewer_models import textured_model


def _state(n: int, iteration: int, seed: int = 0) -> dict:
    """A checkpoint as the trainer writes one (the model and what a resume needs besides)."""
    model = textured_model(n=n, seed=seed)
    return {"model": model.state_dict(), "opt": {"exp_avg": torch.zeros(n, 3)}, "iteration": iteration,
            "rng": ckpt.rng_state(torch.Generator()), "log_lines": 0, "config": {}}


def _log(records: list[dict]) -> str:
    return "".join(json.dumps(r) + "\n" for r in records)


@pytest.fixture
def run(tmp_path) -> str:
    """A run folder as `ctgs train` starts one: its config, its log, an empty checkpoints/ (no scene on disk)."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.toml").write_text(f'scene_dir = "{tmp_path / "gone"}"\nimages = "images"\nholdout = 8\n'
                                     'iterations = 3000\n')
    (run / "log.jsonl").write_text(_log([{"type": "start", "n": 10}]))
    return str(run)


def _live(run: str, tmp_path) -> LiveRun:
    work = tmp_path / "work"
    work.mkdir(exist_ok=True)
    return LiveRun(run, str(work))


def test_a_run_without_a_checkpoint_shows_its_progress_and_no_model(run, tmp_path):
    steps = [{"type": "step", "it": i, "loss": 1.0 / i, "psnr": 10 + i / 100, "n": 10, "texels": 40, "wall": i * 0.5}
             for i in range(1, 1001, 10)]
    records = [{"type": "plan", "it": 0, "time_budget_s": 600.0, "iterations": 2400}] + steps + [
        {"type": "test", "it": 500, "psnr": 18.5, "ssim": 0.6}, {"type": "plan", "it": 900, "iterations": 2200}]
    with open(os.path.join(run, "log.jsonl"), "a") as f:
        f.write(_log(records))
    live = _live(run, tmp_path)
    st = live.status()
    assert st["model"] is None and st["state"] == "stopped"  # no lock holder: not running
    assert st["iteration"] == 991 and st["planned"] == 2200 and st["loss"] == pytest.approx(1 / 991)
    assert st["test"] == [[500, 18.5, 0.6]] and st["loss_curve"][0] == [1, 1.0] and len(st["loss_curve"]) == 100
    assert any("not on this machine" in n for n in st["notes"])  # no cameras: said
    # held by a live training (this process stands in for it): training, and its budget's end is the time left
    (tmp_path / "run" / ".ctgs-lock").write_text(json.dumps({"command": "ctgs train", "pid": os.getpid(),
                                                             "host": socket.gethostname(), "since": 0}))
    st = live.status()
    assert st["state"] == "training"
    assert 600 - 495.5 - 5 <= st["seconds_left"] <= 600 - 495.5  # budget - wall of the last step - since it


def test_the_loss_curve_is_thinned_to_a_bounded_size(run, tmp_path):
    with open(os.path.join(run, "log.jsonl"), "a") as f:
        f.write(_log([{"type": "step", "it": i, "loss": 0.5, "wall": 0.0} for i in range(1, 5 * MAX_CURVE)]))
    st = _live(run, tmp_path).status()
    assert MAX_CURVE // 2 <= len(st["loss_curve"]) <= MAX_CURVE and st["loss_curve"][-1][0] > 4 * MAX_CURVE - 10


def test_each_newer_whole_checkpoint_is_shown_once_and_a_cut_one_never(run, tmp_path):
    live = _live(run, tmp_path)
    ckpt.save_checkpoint(run, _state(12, 100))
    st = live.status()
    assert st["model"]["version"] == 1 and st["model"]["iteration"] == 100 and st["model"]["num_surfels"] == 12
    assert st["model"]["source"] == os.path.join("checkpoints", "last.pt")
    assert live.status()["model"]["version"] == 1  # the same file: not built again
    # a last.pt cut short (as a copy or a failing disk leaves one): passed over, the model shown stays, said
    ckpt.save_checkpoint(run, _state(20, 200))  # the one at 100 becomes prev.pt
    last = ckpt.checkpoint_path(run)
    data = open(last, "rb").read()
    with open(last, "wb") as f:
        f.write(data[: len(data) // 2])
    st = live.status()
    assert st["model"]["version"] == 1 and st["model"]["iteration"] == 100
    assert any("checkpoints/last.pt unreadable" in n for n in st["notes"])
    # the next whole checkpoint lands (written under a hidden name and renamed): shown
    ckpt.save_checkpoint(run, _state(30, 300))
    st = live.status()
    assert st["model"]["version"] == 2 and st["model"]["iteration"] == 300 and st["model"]["num_surfels"] == 30
    assert not any("unreadable" in n for n in st["notes"])  # (an older unreadable file is no news)
    assert live.bundle_dir(2) and live.bundle_dir(1)  # the one before is kept for a page still fetching it
    ckpt.save_checkpoint(run, _state(31, 400))
    assert live.status()["model"]["version"] == 3
    assert live.bundle_dir(1) is None and not os.path.exists(os.path.join(live.work_dir, "v1"))


def test_a_hidden_temporary_checkpoint_is_never_read(run, tmp_path):
    torch.save(_state(12, 100), os.path.join(run, "checkpoints", ".last.pt.tmp-1234-abcdef-k3j4h5g6.pt"))
    assert _live(run, tmp_path).status()["model"] is None


def test_files_linked_from_outside_the_run_folder_are_not_read(run, tmp_path):
    outside = tmp_path / "outside.pt"
    torch.save(_state(12, 100), outside)
    os.symlink(outside, os.path.join(run, "checkpoints", "last.pt"))
    (tmp_path / "other.jsonl").write_text(_log([{"type": "step", "it": 7, "loss": 0.1}]))
    os.remove(os.path.join(run, "log.jsonl"))
    os.symlink(tmp_path / "other.jsonl", os.path.join(run, "log.jsonl"))
    st = _live(run, tmp_path).status()
    assert st["model"] is None and st["iteration"] is None


class CreatesAFile:
    """Unpickled, creates `path`: a pickle may call any function it names."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return open, (self.path, "w")


def test_a_checkpoint_that_names_code_is_refused_and_runs_nothing(run, tmp_path):
    planted = tmp_path / "planted"
    state = _state(12, 100)
    state["opt"] = CreatesAFile(str(planted))
    torch.save(state, ckpt.checkpoint_path(run))
    st = _live(run, tmp_path).status()
    assert st["model"] is None and not planted.exists()
    assert any("checkpoints/last.pt unreadable" in n for n in st["notes"])


def test_the_log_is_read_a_whole_line_at_a_time_and_again_when_rewritten(run, tmp_path):
    path = os.path.join(run, "log.jsonl")
    live = _live(run, tmp_path)
    step = lambda i: json.dumps({"type": "step", "it": i, "loss": 0.5, "wall": float(i)})  # noqa: E731
    with open(path, "a") as f:
        f.write(step(1) + "\n" + "not json\n" + step(2) + "\n" + step(3)[:10])  # a line being written
    assert live.status()["iteration"] == 2
    with open(path, "a") as f:
        f.write(step(3)[10:] + "\n")
    st = live.status()
    assert st["iteration"] == 3 and [p[0] for p in st["loss_curve"]] == [1, 2, 3]
    # a resume cuts the log to its checkpoint (a new, shorter file): read again from its start, nothing counted twice
    tmp = path + ".new"
    with open(tmp, "w") as f:
        f.write(_log([{"type": "start"}]) + step(1) + "\n")
    os.replace(tmp, path)
    st = live.status()
    assert st["iteration"] == 1 and [p[0] for p in st["loss_curve"]] == [1]


def test_a_finished_run_shows_its_model_and_nothing_left(run, tmp_path):
    ckpt.save_checkpoint(run, _state(12, 100))
    torch.save({"model": textured_model(n=16).state_dict(), "iteration": 3000, "scene_dir": "x"},
               os.path.join(run, "model.pt"))
    st = _live(run, tmp_path).status()
    assert st["state"] == "finished" and st["seconds_left"] == 0.0
    assert st["model"]["source"] == "model.pt" and st["model"]["iteration"] == 3000 and st["model"]["num_surfels"] == 16


def _get(url: str, host: str | None = None) -> tuple[int, bytes, dict]:
    req = urllib.request.Request(url, headers={"Host": host} if host else {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.read(), dict(r.headers)
    except urllib.error.HTTPError as exc:
        return exc.code, b"", dict(exc.headers)


def test_the_server_answers_live_routes_with_the_checks_of_every_route(run, tmp_path):
    ckpt.save_checkpoint(run, _state(12, 100))
    with ViewerServer(live=_live(run, tmp_path)) as srv:
        assert srv.url.startswith("http://127.0.0.1:")
        status, body, headers = _get(srv.url + "live/status.json")
        assert status == 200 and json.loads(body)["model"]["version"] == 1
        assert headers["Content-Security-Policy"] == CSP and headers["Cache-Control"] == "no-store"
        status, body, _ = _get(srv.url + "live/1/bundle.json")
        assert status == 200 and json.loads(body)["num_surfels"] == 12
        assert _get(srv.url + "live/1/surfels.bin")[0] == 200
        for path in ("live/2/bundle.json", "live/1/.ctgs-output", "live/1/%2e%2e/v1/bundle.json", "live/1/",
                     "live/x/bundle.json", "bundle/bundle.json", "live/status.json/x"):
            assert _get(srv.url + path)[0] == 404, path
        # DNS rebinding: a page elsewhere that reaches the port under its own name gets nothing, live routes included
        port = srv.url.rsplit(":", 1)[1].rstrip("/")
        for path in ("live/status.json", "live/1/bundle.json"):
            assert _get(srv.url + path, host=f"evil.example:{port}")[0] == 421
    # a bundle's viewer has no live routes
    web = tmp_path / "web"
    from ctgs.formats.web_bundle import write_web_bundle

    write_web_bundle(textured_model(n=5), str(web), [])
    with ViewerServer(str(web)) as srv:
        assert _get(srv.url + "live/status.json")[0] == 404


def test_ctgs_view_follows_a_run_folder(run, tmp_path, monkeypatch):
    import ctgs.viewer.server

    ckpt.save_checkpoint(run, _state(12, 100))
    seen = {}

    serve = ctgs.viewer.server.ViewerServer.serve_forever

    def serve_once(self):
        thread = threading.Thread(target=serve, args=(self,), daemon=True)
        thread.start()
        seen["status"] = json.loads(_get(self.url + "live/status.json")[1])
        self.httpd.shutdown()
        thread.join()
        raise KeyboardInterrupt  # as Ctrl-C ends the command

    monkeypatch.setattr(ctgs.viewer.server.ViewerServer, "serve_forever", serve_once)
    assert is_run_folder(run) and not is_run_folder(os.path.join(run, "checkpoints"))
    res = CliRunner().invoke(main, ["view", run, "--port", "0", "--no-browser"])
    assert res.exit_code == 0, res.output
    assert "a run folder, followed as it trains" in res.output and "is not on this machine" in res.output
    assert seen["status"]["model"]["iteration"] == 100
    assert sorted(os.listdir(run)) == ["checkpoints", "config.toml", "log.jsonl"]  # nothing written there
    res = CliRunner().invoke(main, ["view", run, "--mesh", str(tmp_path / "m.ply"), "--no-browser"])
    assert res.exit_code == 2 and "without a mesh" in res.output and len(res.output.strip().splitlines()) == 1
    shutil.rmtree(run)


def test_a_run_folder_that_just_started_is_followed_once_its_config_lands(tmp_path):
    from ctgs.io import owner
    from ctgs.scene.demo import make_demo_scene

    run = tmp_path / "run"
    run.mkdir()
    owner.mark(str(run), "run")  # what `ctgs train` writes first
    assert is_run_folder(str(run))
    live = _live(str(run), tmp_path)
    st = live.status()
    assert st["model"] is None and st["iteration"] is None and live.cameras == []
    scene = make_demo_scene(str(tmp_path / "scene"), num_views=9, width=40, height=32, points=200, supersample=1)
    (run / "config.toml").write_text(f'scene_dir = "{scene}"\nimages = "images"\nholdout = 8\n')
    live.status()
    assert len(live.cameras) == 9 and not any("not on this machine" in n for n in live.status()["notes"])
