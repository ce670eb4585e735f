"""ctgs.io.atomic: complete or absent, never half-written, and nothing left behind on failure."""

from __future__ import annotations

import errno
import os
import signal
import stat

import pytest
import torch

from ctgs.errors import Terminated, describe_os_error
from ctgs.io import atomic
from ctgs.io.signals import signals_deferred


class Boom(Exception):
    pass


def _names(folder) -> list[str]:
    return sorted(os.listdir(folder))


def test_files_appear_whole_with_ordinary_permissions(tmp_path):
    atomic.write_text(str(tmp_path / "a.txt"), "x\r\ny")
    atomic.write_bytes(str(tmp_path / "b.bin"), b"\x00\x01")
    atomic.write_json(str(tmp_path / "sub" / "c.json"), {"k": [1, 2]})
    atomic.torch_save({"t": torch.arange(3)}, str(tmp_path / "d.pt"))
    assert (tmp_path / "a.txt").read_bytes() == b"x\r\ny"  # written as given, no newline translation
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
    assert (tmp_path / "sub" / "c.json").read_text() == '{\n  "k": [\n    1,\n    2\n  ]\n}\n'
    assert torch.equal(torch.load(tmp_path / "d.pt", weights_only=True)["t"], torch.arange(3))
    assert stat.S_IMODE(os.stat(tmp_path / "a.txt").st_mode) == atomic.FILE_MODE
    assert _names(tmp_path) == ["a.txt", "b.bin", "d.pt", "sub"]  # no temporaries left


def test_failed_file_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "report.json"
    atomic.write_text(str(path), "old")
    with pytest.raises(Boom):
        with atomic.atomic_path(str(path)) as tmp:
            assert tmp.endswith(".json") and os.path.dirname(tmp) == str(tmp_path)
            open(tmp, "w").write("half")
            raise Boom
    assert path.read_text() == "old" and _names(tmp_path) == ["report.json"]


def test_folder_is_built_aside_and_swapped_in(tmp_path):
    out = tmp_path / "model"
    with atomic.atomic_dir(str(out)) as tmp:
        open(os.path.join(tmp, "one"), "w").write("1")
        assert not out.exists()  # nothing under the final name until the block succeeds
    assert _names(out) == ["one"] and stat.S_IMODE(os.stat(out).st_mode) == atomic.DIR_MODE
    with atomic.atomic_dir(str(out)) as tmp:  # replace: the new content only, the old folder deleted
        open(os.path.join(tmp, "two"), "w").write("2")
    assert _names(out) == ["two"] and _names(tmp_path) == ["model"]


def test_failed_folder_leaves_the_old_one_and_no_temporary(tmp_path):
    out = tmp_path / "eval"
    with atomic.atomic_dir(str(out)) as tmp:
        open(os.path.join(tmp, "metrics.json"), "w").write("{}")
    with pytest.raises(Boom):
        with atomic.atomic_dir(str(out)) as tmp:
            os.makedirs(os.path.join(tmp, "renders"))
            raise Boom
    assert _names(out) == ["metrics.json"] and _names(tmp_path) == ["eval"]
    with pytest.raises(Boom):
        with atomic.atomic_dir(str(tmp_path / "new")):
            raise Boom
    assert _names(tmp_path) == ["eval"]


def test_no_replace_refuses_an_existing_folder(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep").write_text("k")
    with pytest.raises(FileExistsError):
        with atomic.atomic_dir(str(tmp_path / "x"), replace=False) as tmp:
            open(os.path.join(tmp, "new"), "w").write("n")
    assert _names(tmp_path / "x") == ["keep"] and _names(tmp_path) == ["x"]


def test_an_existing_folder_is_named_in_the_one_line(tmp_path):
    (tmp_path / "x").mkdir()
    with pytest.raises(FileExistsError) as info:
        with atomic.atomic_dir(str(tmp_path / "x"), replace=False):
            pass
    assert info.value.filename == str(tmp_path / "x") and info.value.errno == errno.EEXIST
    line = describe_os_error(info.value)
    assert line == f"{tmp_path / 'x'}: already exists; choose another output (-o); ctgs does not write over it"


@pytest.mark.parametrize("replace", [False, True])
def test_a_folder_another_writer_renames_in_first_is_treated_as_there_before(tmp_path, monkeypatch, replace):
    """Between the existence check and the rename another writer puts its complete folder there (the rename then
    fails with ENOTEMPTY): refused by name without replace, replaced with it, never an unnamed error."""
    out = tmp_path / "x"
    real_lexists = os.path.lexists

    def theirs_lands_after_the_check(path):
        seen = real_lexists(path)
        if path == str(out) and not real_lexists(out):
            out.mkdir()
            (out / "theirs").write_text("t")
        return seen

    monkeypatch.setattr(atomic.os.path, "lexists", theirs_lands_after_the_check)
    if replace:
        with atomic.atomic_dir(str(out)) as tmp:
            open(os.path.join(tmp, "mine"), "w").write("m")
        assert _names(out) == ["mine"]
    else:
        with pytest.raises(FileExistsError):
            with atomic.atomic_dir(str(out), replace=False) as tmp:
                open(os.path.join(tmp, "mine"), "w").write("m")
        assert _names(out) == ["theirs"]
    assert _names(tmp_path) == ["x"]


class _SignalsWhilePickled:
    """Sends SIGTERM to this process while torch.save pickles it: a stop landing mid-write, deterministically."""

    def __reduce__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        return (dict, ())


def test_a_stop_during_torch_save_lands_after_the_file_is_whole(tmp_path):
    """The CLI's SIGTERM handler raised inside torch.save's zip writer, whose __exit__ then failed ("unexpected pos"):
    the stop became a RuntimeError (exit 1, a traceback). Now the save completes and the stop is raised after it."""
    path = str(tmp_path / "last.pt")
    before = signal.getsignal(signal.SIGTERM)

    def stop(signum, frame):
        raise Terminated(signum)

    signal.signal(signal.SIGTERM, stop)
    try:
        with pytest.raises(Terminated):
            atomic.torch_save({"w": torch.arange(1000.0), "x": _SignalsWhilePickled()}, path)
        assert signal.getsignal(signal.SIGTERM) is stop  # the handler is back in place
    finally:
        signal.signal(signal.SIGTERM, before)
    with torch.serialization.safe_globals([dict]):  # what _SignalsWhilePickled pickles as
        state = torch.load(path, weights_only=True)
    assert torch.equal(state["w"], torch.arange(1000.0)) and state["x"] == {}
    assert os.listdir(tmp_path) == ["last.pt"]


def test_signals_deferred_holds_a_signal_and_delivers_it_once_after(tmp_path):
    calls = []
    before = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, lambda s, f: calls.append(s))
    try:
        with signals_deferred():
            pass
        assert calls == []
        with signals_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):  # give the interpreter bytecode boundaries to run the (holding) handler
                pass
            assert calls == []
        assert calls == [signal.SIGINT]  # held, then delivered once
    finally:
        signal.signal(signal.SIGINT, before)
