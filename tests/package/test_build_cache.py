"""The extension's per-user build folder, its one-line build message and the missing-compiler errors.

None of these tests compiles anything: torch's builder is replaced by a stand-in where a build would start.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import pytest

import ctgs.ops.ext as ext
import ctgs.resources as resources
from ctgs.errors import UserError

CPU_FLAGS = {"extra_cflags": ext.CPU_CFLAGS, "extra_ldflags": ext.CPU_LDFLAGS}


@pytest.fixture
def cache(monkeypatch, tmp_path) -> Path:
    monkeypatch.setenv("CTGS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("TORCH_EXTENSIONS_DIR", raising=False)
    return tmp_path / "cache"


def test_build_folder_is_in_the_user_cache_not_the_package(cache):
    key = ext.build_key("ctgs_cpu", CPU_FLAGS)
    folder = ext.build_dir("ctgs_cpu", key)
    assert folder == cache / "torch_extensions" / f"ctgs_cpu-{key}"
    assert resources.PACKAGE_DIR not in folder.parents and resources.kernels_dir() not in folder.parents


def test_torch_extensions_dir_is_honoured(cache, monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "te"))
    assert ext.build_dir("ctgs_cpu", "abc") == tmp_path / "te" / "ctgs_cpu"


def test_build_key_follows_sources_headers_and_flags(monkeypatch, tmp_path):
    copy = tmp_path / "kernels"
    shutil.copytree(resources.kernels_dir(), copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(ext, "kernels_dir", lambda: copy)
    base = ext.build_key("ctgs_cpu", CPU_FLAGS)
    assert ext.build_key("ctgs_cpu", CPU_FLAGS) == base  # deterministic
    assert ext.build_key("ctgs_cpu", {**CPU_FLAGS, "extra_cflags": ["-O2"]}) != base
    assert ext.build_key("ctgs_cuda", CPU_FLAGS) != base
    header = copy / "include" / "ctgs" / "constants.h"
    header.write_text(header.read_text() + "\n// changed\n")  # torch's own check would not see a header
    assert ext.build_key("ctgs_cpu", CPU_FLAGS) != base
    monkeypatch.delenv("CXX", raising=False)
    with_cxx_default = ext.build_key("ctgs_cpu", CPU_FLAGS)
    monkeypatch.setenv("CXX", "clang++")  # another compiler, another build
    assert ext.build_key("ctgs_cpu", CPU_FLAGS) != with_cxx_default
    (copy / "notes.txt").write_text("not a source")  # only sources and headers count
    with_notes = ext.build_key("ctgs_cpu", CPU_FLAGS)
    (copy / "notes.txt").write_text("changed")
    assert ext.build_key("ctgs_cpu", CPU_FLAGS) == with_notes


def test_one_line_message_only_when_a_build_starts(cache, monkeypatch, capsys):
    from torch.utils import cpp_extension

    calls = []

    def fake_load(**kwargs):
        calls.append(kwargs)
        return types.ModuleType(kwargs["name"])

    monkeypatch.setattr(cpp_extension, "load", fake_load)
    ext.jit_build("ctgs_cpu", ext.CPU_SOURCES, what="CPU", fallback="reference", verbose=False,
                  first_use="~1 min", **CPU_FLAGS)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "building the CPU renderer extension (first use, ~1 min)" in err
    folder = Path(calls[0]["build_directory"])
    assert folder.parent == cache / "torch_extensions" and (folder / ext.BUILT_MARKER).is_file()
    assert calls[0]["sources"][0] == str(resources.kernels_dir() / "bindings.cpp")
    ext.jit_build("ctgs_cpu", ext.CPU_SOURCES, what="CPU", fallback="reference", verbose=False,
                  first_use="~1 min", **CPU_FLAGS)
    assert capsys.readouterr().err == ""  # built before: loading says nothing


def test_two_checkouts_with_the_same_kernels_never_share_a_build(monkeypatch, tmp_path):
    # torch writes absolute paths into build.ninja: a folder shared by two checkouts (or venvs) was rebuilt at every
    # switch between them. The same kernels at another path get another key; the same path keeps its key.
    keys = {}
    for where in ("a", "b"):
        copy = tmp_path / where / "kernels"
        shutil.copytree(resources.kernels_dir(), copy, ignore=shutil.ignore_patterns("__pycache__"))
        monkeypatch.setattr(ext, "kernels_dir", lambda copy=copy: copy)
        keys[where] = ext.build_key("ctgs_cpu", CPU_FLAGS)
        assert ext.build_key("ctgs_cpu", CPU_FLAGS) == keys[where]
    assert keys["a"] != keys["b"]
    import torch

    monkeypatch.setattr(torch, "__file__", str(tmp_path / "other-venv" / "torch" / "__init__.py"))
    assert ext.build_key("ctgs_cpu", CPU_FLAGS) != keys["b"]  # another torch install: its own build


def test_a_recompile_of_a_built_folder_is_announced(cache, monkeypatch, capsys):
    import time

    from torch.utils import cpp_extension

    delay = {"s": 0.0}

    def fake_load(**kwargs):
        time.sleep(delay["s"])
        return types.ModuleType(kwargs["name"])

    monkeypatch.setattr(cpp_extension, "load", fake_load)
    monkeypatch.setattr(ext, "BUILD_NOTE_S", 0.05)
    build = lambda: ext.jit_build("ctgs_cpu", ext.CPU_SOURCES, what="CPU", fallback="reference",  # noqa: E731
                                  verbose=False, first_use="~1 min", **CPU_FLAGS)
    build()
    assert "building the CPU renderer extension" in capsys.readouterr().err
    build()  # up to date: quick and silent
    time.sleep(0.1)
    assert capsys.readouterr().err == ""
    delay["s"] = 0.3  # torch found the sources touched and compiles again
    build()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "recompiling the CPU renderer extension" in err


def test_failed_build_leaves_no_marker(cache, monkeypatch, capsys):
    from torch.utils import cpp_extension

    def failing_load(**kwargs):
        raise RuntimeError("Error building extension 'ctgs_cpu'")

    monkeypatch.setattr(cpp_extension, "load", failing_load)
    for _ in range(2):  # the message comes back on the next attempt
        with pytest.raises(UserError, match="Error building extension 'ctgs_cpu'.*CTGS_VERBOSE_BUILD=1"):
            ext.jit_build("ctgs_cpu", ext.CPU_SOURCES, what="CPU", fallback="reference", verbose=False,
                          first_use="~1 min", **CPU_FLAGS)
        assert "building the CPU renderer" in capsys.readouterr().err
    assert not list(cache.rglob(ext.BUILT_MARKER))


def test_missing_compiler_named(monkeypatch, tmp_path):
    monkeypatch.setattr(ext, "_cpu_module", None)
    monkeypatch.setenv("CXX", str(tmp_path / "nowhere" / "g++"))
    with pytest.raises(UserError, match=r"C\+\+ compiler not found \(\$CXX=.*nowhere/g\+\+\).*--backend reference"):
        ext.load_cpu()
    monkeypatch.delenv("CXX")
    monkeypatch.setenv("PATH", str(tmp_path))  # an empty folder: no c++ anywhere
    with pytest.raises(UserError, match=r"C\+\+ compiler not found \(`c\+\+` on PATH\).*apt-get install g\+\+"):
        ext.load_cpu()


def test_missing_nvcc_named(monkeypatch):
    import torch
    from torch.utils import cpp_extension

    import ctgs.ops.ext_cuda as ext_cuda

    monkeypatch.setattr(ext_cuda, "_cuda_module", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # pretend a GPU, never build
    monkeypatch.setattr(cpp_extension, "CUDA_HOME", None)
    with pytest.raises(UserError, match=r"CUDA compiler nvcc not found \(not on PATH and CUDA_HOME unset\)"):
        ext_cuda.load_cuda()


def test_missing_compiler_from_the_cli(tmp_path):
    """The user sees one error line and a non-zero exit (no traceback), in a fresh process."""
    code = ("import sys; from ctgs.cli import main; sys.argv = ['ctgs', 'render', sys.argv[1], '-o', sys.argv[2], "
            "'--backend', 'cpu']; main()")
    run = _tiny_run(tmp_path)
    env = {"PATH": str(tmp_path), "CTGS_CACHE_DIR": str(tmp_path / "cache"), "HOME": str(tmp_path)}
    p = subprocess.run([sys.executable, "-c", code, run, str(tmp_path / "out")], capture_output=True, text=True,
                       env=env, timeout=120)
    assert p.returncode != 0, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: C++ compiler not found (`c++` on PATH)"), p.stderr


def _tiny_run(tmp_path: Path) -> str:
    """A run folder whose model the render stage can load (its scene: a 3-view demo scene)."""
    import torch

    from ctgs.scene.demo import make_demo_scene

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "eval"))
    from fixture_run import point_model

    from ctgs.scene import load_scene

    scene_dir = make_demo_scene(str(tmp_path / "scene"), num_views=3, width=16, height=16, points=100,
                                supersample=1)
    scene = load_scene(scene_dir, holdout=2, load_images=False)
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"model": point_model(scene.points, scene.point_colors, n=10).state_dict(), "scene_dir": scene_dir,
                "images": "images", "holdout": 2, "iteration": 1, "config": {}}, run / "model.pt")
    return str(run)


def test_one_ninja_whatever_path_holds(monkeypatch, tmp_path):
    """`venv/bin/ctgs` run without activating the venv (no ninja on PATH), or with another ninja first on PATH (the
    system's): every build runs the pip package's ninja, so the build folder is never rebuilt at a switch."""
    ninja = pytest.importorskip("ninja")
    own = os.path.join(ninja.BIN_DIR, "ninja")
    monkeypatch.setenv("PATH", str(tmp_path))
    assert shutil.which("ninja") is None
    assert ext.ninja_binary("reference") == own
    other = tmp_path / "ninja"
    other.write_text("#!/bin/sh\necho 1.0.0\n")
    other.chmod(0o755)
    assert shutil.which("ninja") == str(other)
    assert ext.ninja_binary("reference") == own
    with ext._first_on_path(os.path.dirname(own)):
        assert shutil.which("ninja") == own  # what torch's build runs
    assert os.environ["PATH"] == str(tmp_path)


def test_the_build_key_names_the_ninja(tmp_path):
    """Another ninja (another version) gets its own build folder rather than rebuilding the other's."""
    fake = tmp_path / "ninja"
    fake.write_text("#!/bin/sh\necho 1.0.0\n")
    fake.chmod(0o755)
    own = ext.ninja_binary("reference")
    assert ext.build_key("ctgs_cpu", CPU_FLAGS, own) == ext.build_key("ctgs_cpu", CPU_FLAGS, own)
    assert ext.build_key("ctgs_cpu", CPU_FLAGS, str(fake)) != ext.build_key("ctgs_cpu", CPU_FLAGS, own)


def test_a_build_killed_while_compiling_blocks_no_later_load(tmp_path):
    """torch's baton (a file `lock`) stays when a load is killed mid-build; the next load waits for the build that
    load left running (a process working in the folder), then goes on instead of waiting for the baton forever."""
    folder = tmp_path / "build"
    folder.mkdir()
    (folder / ext.TORCH_BATON).write_text("")
    left = subprocess.Popen(["sleep", "2"], cwd=folder)  # the dead load's ninja, still compiling
    t0 = time.monotonic()
    with ext._one_builder(folder):
        # waited for it: a process leaves /proc's cwd a moment before waitpid can reap it, so reap with a timeout
        assert time.monotonic() - t0 > 1.0
        assert left.wait(timeout=10) == 0
        assert not (folder / ext.TORCH_BATON).exists()
    # while another process holds the folder (a build under way), a load waits for it
    held = os.open(folder / ext.BUILD_LOCK, os.O_RDWR)
    fcntl.flock(held, fcntl.LOCK_EX)
    entered = threading.Event()

    def load():
        with ext._one_builder(folder):
            entered.set()

    waiter = threading.Thread(target=load)
    waiter.start()
    assert not entered.wait(0.5)
    os.close(held)  # the builder ended, however it ended
    assert entered.wait(10)
    waiter.join()
