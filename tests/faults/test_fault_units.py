"""The pieces the fault suite's end-to-end cases rest on, each alone: the one-line description of an OSError, the
sweep of dead writers' temporaries (and never a live one's), an image write that fails silently inside
OpenImageIO, and the checkpoint kept before the last."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from ctgs.errors import OS_ERROR_EXIT, UserError, describe_os_error
from ctgs.io import atomic, images
from ctgs.runs import checkpoint as ckpt
from fault_helpers import can_mount, small_fs


@pytest.mark.parametrize(("code", "words"), [
    (errno.ENOSPC, "no space left on the device; free space there"),
    (errno.EROFS, "read-only filesystem; write the output to a writable folder"),
    (errno.EACCES, "permission denied; check its permissions"),
    (errno.EIO, "input/output error"),
    (errno.ENODEV, "no such device"),
])
def test_os_errors_are_one_line_naming_the_path_and_the_fix(code, words):
    line = describe_os_error(OSError(code, os.strerror(code), "/data/out/model.pt"))
    assert line.startswith("/data/out/model.pt: ") and words in line and "\n" not in line
    # a library's own detail is kept, the path still first
    line = describe_os_error(OSError(code, "3 MiB free, need 9 MiB", "/data"))
    assert line.startswith("/data: ") and "(3 MiB free, need 9 MiB)" in line


def test_cli_prints_one_line_and_exits_74_or_shows_the_traceback_when_asked(monkeypatch):
    import click
    from click.testing import CliRunner

    import ctgs.cli as cli_mod

    @click.command(name="boom")
    def boom():
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/full/disk/out.png")

    monkeypatch.setitem(cli_mod.STAGES, "boom", ("fake", "a stage that hits a full disk"))
    monkeypatch.setattr(cli_mod.LazyGroup, "get_command", lambda self, ctx, name: boom if name == "boom" else None)
    result = CliRunner().invoke(cli_mod.main, ["boom"])
    assert result.exit_code == OS_ERROR_EXIT
    assert result.stderr.strip().splitlines() == [
        "error: /full/disk/out.png: no space left on the device; free space there or write the output elsewhere (-o)"]
    monkeypatch.setenv("CTGS_TRACEBACK", "1")
    assert isinstance(CliRunner().invoke(cli_mod.main, ["boom"]).exception, OSError)


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_sweep_removes_dead_writers_temporaries_only(tmp_path):
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        dead, here = _dead_pid(), atomic._HOST
        other = "0" * 6 if here != "0" * 6 else "1" * 6
        names = {
            f".model.tmp-{dead}-{here}-abcd1234": "dir",  # a folder a killed export was building
            f".a.png.tmp-{dead}-{here}-zz_9zz9z.png": "file",  # a killed image write
            f".b.png.tmp-{live.pid}-{here}-abcdefgh.png": "file",  # another run writing right now: kept
            f".c.json.tmp-{os.getpid()}-{here}-abcdefgh.json": "file",  # ours: kept
            f".e.json.tmp-{dead}-{other}-abcdefgh.json": "file",  # another machine's (a network share): kept
            f".f.json.tmp-{dead}-{other}-abcdefgh.json": "old",  # ... unless two days old
            ".old.json.tmp-abcdefgh.json": "old",  # named before ids, two days old: removed
            ".new.json.tmp-abcdefgh.json": "file",  # named before ids, recent: kept (its writer may be alive)
            ".bashrc.tmp-notours": "old",  # not a name the helpers make: never touched
            "report.json": "old",
        }
        for name, kind in names.items():
            path = tmp_path / name
            if kind == "dir":
                path.mkdir()
                (path / "manifest.json").write_text("{}")
            else:
                path.write_text("x")
            if kind == "old":
                os.utime(path, (time.time() - 2 * 86400,) * 2)
        removed = atomic.sweep_temps(str(tmp_path))
        assert sorted(removed) == sorted([f".model.tmp-{dead}-{here}-abcd1234",
                                          f".a.png.tmp-{dead}-{here}-zz_9zz9z.png",
                                          f".f.json.tmp-{dead}-{other}-abcdefgh.json", ".old.json.tmp-abcdefgh.json"])
        assert sorted(os.listdir(tmp_path)) == sorted(set(names) - set(removed))
        # the next write into the folder sweeps too
        (tmp_path / f".d.txt.tmp-{dead}-{here}-abcdefgh.txt").write_text("half")
        atomic.write_text(str(tmp_path / "d.txt"), "whole")
        assert f".d.txt.tmp-{dead}-{here}-abcdefgh.txt" not in os.listdir(tmp_path)
    finally:
        live.kill()
        live.wait()


class _SilentlyFailingOutput:
    """An ImageOutput that reports success at every step and writes nothing (OpenImageIO on a full disk)."""

    def open(self, *args):
        return True

    def write_image(self, *args):
        return True

    def geterror(self):
        return ""

    def close(self):
        return True


def test_an_image_write_that_failed_silently_is_an_oserror_and_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(images.oiio.ImageOutput, "create", staticmethod(lambda path: _SilentlyFailingOutput()))
    with pytest.raises(OSError) as err:
        images.write_image(str(tmp_path / "view.png"), np.zeros((8, 8, 3), np.float32))
    assert err.value.filename == str(tmp_path / "view.png")
    assert os.listdir(tmp_path) == []


def test_image_writes_are_read_back_whole(tmp_path):
    for name in ("a.png", "b.jpg", "c.exr", "d.tif"):
        images.write_image(str(tmp_path / name), np.random.default_rng(0).random((9, 7, 3)).astype(np.float32))
        assert images.read_image(str(tmp_path / name)).shape == (9, 7, 3)
    assert sorted(os.listdir(tmp_path)) == ["a.png", "b.jpg", "c.exr", "d.tif"]


@pytest.mark.parametrize("name", ["a.png", "b.jpg", "c.png"])
def test_a_cut_or_damaged_png_or_jpeg_is_found_by_its_structure(tmp_path, name):
    channels = 4 if name == "c.png" else 3
    pixels = np.random.default_rng(1).random((13, 11, channels)).astype(np.float32)
    images.write_image(str(tmp_path / name), pixels)
    data = (tmp_path / name).read_bytes()
    check = ((lambda d, w, h: images._png_problem(d, w, h, channels)) if name.endswith(".png")
             else images._jpeg_problem)
    assert check(data, 11, 13) is None
    assert check(data, 12, 13)  # another size
    for cut in (len(data) // 3, len(data) - 1):
        assert check(data[:cut], 11, 13)
    if name.endswith(".png"):  # one flipped byte inside the image data: a CRC no longer matches
        flipped = bytearray(data)
        flipped[len(data) // 2] ^= 0xFF
        assert "damaged" in check(bytes(flipped), 11, 13)


def test_checking_a_written_png_leaves_stderr_alone(tmp_path, monkeypatch):
    """Renders are written while a progress display runs in another thread: the check after the write must not
    point the process's stderr elsewhere, even for a moment."""
    def no_redirect():
        raise AssertionError("stderr redirected")

    monkeypatch.setattr(images, "stderr_silenced", no_redirect)
    images.write_image(str(tmp_path / "view.png"), np.zeros((5, 6, 3), np.float32))
    images.write_image(str(tmp_path / "view.jpg"), np.zeros((5, 6, 3), np.float32))


def test_checkpoints_keep_the_one_before_and_fall_back_to_it(tmp_path, capsys):
    run = str(tmp_path)
    os.makedirs(os.path.join(run, "checkpoints"))
    assert ckpt.load_checkpoint(run) is None and not ckpt.has_checkpoint(run)
    for it in (10, 20, 30):
        ckpt.save_checkpoint(run, {"iteration": it, "model": {"x": torch.arange(it)}})
    assert torch.load(ckpt.previous_path(run), weights_only=True)["iteration"] == 20
    assert ckpt.load_checkpoint(run)["iteration"] == 30 and capsys.readouterr().err == ""
    with open(ckpt.checkpoint_path(run), "r+b") as f:
        f.truncate(64)
    assert ckpt.load_checkpoint(run)["iteration"] == 20
    assert "resuming from the checkpoint before it" in capsys.readouterr().err
    # the damaged last.pt is set aside, so the next save keeps the good prev.pt as the one before
    assert sorted(os.listdir(os.path.join(run, "checkpoints"))) == ["last.pt.unreadable", "prev.pt"]
    ckpt.save_checkpoint(run, {"iteration": 21, "model": {}})
    assert torch.load(ckpt.previous_path(run), weights_only=True)["iteration"] == 20
    os.remove(ckpt.checkpoint_path(run))  # killed between the two renames: prev.pt alone
    assert ckpt.has_checkpoint(run) and ckpt.load_checkpoint(run)["iteration"] == 20
    with open(ckpt.previous_path(run), "wb") as f:
        f.write(b"\x80\x04garbage")
    with pytest.raises(UserError, match="prev.pt unreadable.*no readable checkpoint"):
        ckpt.load_checkpoint(run)
    assert sorted(os.listdir(os.path.join(run, "checkpoints"))) == ["last.pt.unreadable", "prev.pt"]


def test_two_writers_of_one_path_never_share_a_temporary(tmp_path):
    # spz once wrote through a fixed OUT.spz.tmp: two exports to one path wrote into the same file
    path = str(tmp_path / "m.spz")
    with atomic.atomic_path(path) as a, atomic.atomic_path(path) as b:
        assert a != b and os.path.dirname(a) == os.path.dirname(b) == str(tmp_path)
        open(a, "wb").write(b"first")
        open(b, "wb").write(b"second")
    assert open(path, "rb").read() == b"first" and os.listdir(tmp_path) == ["m.spz"]


@pytest.mark.skipif(not can_mount(), reason="a full disk here is a small tmpfs, which needs root")
def test_a_download_onto_a_full_disk_names_the_partial_file_not_the_network(tmp_path):
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    from ctgs.io.download import download

    data = np.random.default_rng(0).bytes(300_000)

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (http.server API)
            self.send_response(200)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, *args):
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        with small_fs(128) as fs:
            dest = os.path.join(fs, "scene.zip")
            with pytest.raises(OSError) as err:
                download(f"http://127.0.0.1:{httpd.server_address[1]}/scene.zip", dest, quiet=True)
            assert err.value.errno == errno.ENOSPC and err.value.filename == dest + ".part"
            assert describe_os_error(err.value).startswith(f"{dest}.part: no space left on the device")
            assert not os.path.exists(dest)
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_a_model_the_user_may_not_read_is_a_permission_error_not_a_corrupt_file(tmp_path, monkeypatch):
    # (root reads any file: the refusal is injected where torch opens it)
    from click.testing import CliRunner

    from ctgs.cli import main

    run = tmp_path / "run"
    run.mkdir()
    (run / "model.pt").write_bytes(b"x")

    def refused(path, *args, **kwargs):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))

    monkeypatch.setattr(torch, "load", refused)
    result = CliRunner().invoke(main, ["export", str(run), "-o", str(tmp_path / "out")])
    assert result.exit_code == OS_ERROR_EXIT
    assert result.stderr.strip().splitlines() == [f"error: {run / 'model.pt'}: permission denied; check its "
                                                  "permissions and its folder's (ls -l); for an output, choose a "
                                                  "folder you may write to (-o)"]


def test_a_checkpoint_the_machine_cannot_read_is_not_taken_for_a_damaged_one(tmp_path, monkeypatch):
    run = str(tmp_path)
    os.makedirs(os.path.join(run, "checkpoints"))
    for it in (10, 20):
        ckpt.save_checkpoint(run, {"iteration": it, "model": {}})

    def failing_device(path, *args, **kwargs):
        raise OSError(errno.EIO, os.strerror(errno.EIO), str(path))

    monkeypatch.setattr(torch, "load", failing_device)
    with pytest.raises(OSError) as err:
        ckpt.load_checkpoint(run)
    assert err.value.errno == errno.EIO and err.value.filename == ckpt.checkpoint_path(run)
    assert sorted(os.listdir(os.path.join(run, "checkpoints"))) == ["last.pt", "prev.pt"]  # nothing set aside
