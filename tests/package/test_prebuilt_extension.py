"""Prebuilt extensions (ctgs.ops.ext.load_prebuilt): under CTGS_PREBUILT=1 an extension built elsewhere, with a
prebuilt.json matching this machine, is imported instead of built, and its ops resolve as after a build (the op
schemas are declared before the library registers its kernels for them); one that differs is named and not used."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

import ctgs.ops.ext as ext

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CPU_FLAGS = {"extra_cflags": ext.CPU_CFLAGS, "extra_ldflags": ext.CPU_LDFLAGS}

PROBE = """
import torch
from ctgs.ops.ext import load_cpu
load_cpu()
means = torch.zeros(2, 3)
quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
out = torch.ops.ctgs.camera_space(means, quats, torch.eye(4), 1)
print("ops ok", len(out))
"""


def _prebuilt(cache, module, name="ctgs_cpu-elsewhere"):
    """A copy of the built extension `module` in `cache`, marked prebuilt as benchmarks/device/build_extensions.py
    marks its builds."""
    folder = cache / "torch_extensions" / name
    folder.mkdir(parents=True)
    shutil.copy(module.__file__, folder / "ctgs_cpu.so")
    copy = type(module)("ctgs_cpu")
    copy.__file__ = str(folder / "ctgs_cpu.so")
    ext.write_prebuilt_manifest(copy, "ctgs_cpu", CPU_FLAGS)
    return folder


def test_a_prebuilt_extension_is_imported_and_its_ops_resolve(tmp_path):
    folder = _prebuilt(tmp_path / "cache", ext.load_cpu())
    assert json.loads((folder / ext.PREBUILT_MANIFEST).read_text()) == ext.prebuilt_manifest("ctgs_cpu", CPU_FLAGS)

    env = dict(os.environ, CTGS_PREBUILT="1", CTGS_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=ROOT)
    env.pop("TORCH_EXTENSIONS_DIR", None)
    done = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"prebuilt {folder / 'ctgs_cpu.so'} loaded" in done.stderr
    assert "building" not in done.stderr, done.stderr  # nothing compiled, no build folder of this machine's made
    assert [p.name for p in (tmp_path / "cache" / "torch_extensions").iterdir()] == [folder.name]
    assert "ops ok 2" in done.stdout


def test_a_prebuilt_extension_that_differs_is_not_used(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CTGS_CACHE_DIR", str(tmp_path / "cache"))
    folder = _prebuilt(tmp_path / "cache", ext.load_cpu())
    manifest = json.loads((folder / ext.PREBUILT_MANIFEST).read_text())
    (folder / ext.PREBUILT_MANIFEST).write_text(json.dumps(dict(manifest, torch="0.0.1")))
    assert ext.load_prebuilt("ctgs_cpu", CPU_FLAGS) is None
    err = capsys.readouterr().err
    assert "ctgs_cpu-elsewhere differs: {'torch': ('0.0.1'" in err and "no prebuilt ctgs_cpu matches" in err


def test_without_the_switch_prebuilt_extensions_are_not_looked_for(tmp_path, monkeypatch):
    monkeypatch.setenv("CTGS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("CTGS_PREBUILT", raising=False)
    looked = []
    monkeypatch.setattr(ext, "load_prebuilt", lambda *a: looked.append(a))
    monkeypatch.setattr(ext, "ninja_binary", lambda fallback: (_ for _ in ()).throw(RuntimeError("build")))
    with pytest.raises(RuntimeError, match="build"):
        ext.jit_build("ctgs_cpu", ext.CPU_SOURCES, what="CPU", fallback="reference", verbose=False, first_use="",
                      **CPU_FLAGS)
    assert looked == []
