"""benchmarks/device/sitecustomize.py: on a GPU machine without network, an extension built on the dev machine is
imported instead of built, and its ops must resolve as after a build (the op schemas are declared before the library
registers its kernels for them)."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys

from ctgs.ops import ext

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
HOOK_DIR = os.path.join(ROOT, "benchmarks", "device")

PROBE = """
import torch
from ctgs.ops.ext import load_cpu
load_cpu()
means = torch.zeros(2, 3)
quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
out = torch.ops.ctgs.camera_space(means, quats, torch.eye(4), 1)
print("ops ok", len(out))
"""


def test_a_prebuilt_extension_is_imported_and_its_ops_resolve(tmp_path):
    module = ext.load_cpu()
    spec = importlib.util.spec_from_file_location("device_hook", os.path.join(HOOK_DIR, "sitecustomize.py"))
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)  # without CTGS_PREBUILT it only defines prebuilt_manifest
    folder = tmp_path / "cache" / "torch_extensions" / "ctgs_cpu-prebuilt"
    folder.mkdir(parents=True)
    shutil.copy(module.__file__, folder / "ctgs_cpu.so")
    manifest = hook.prebuilt_manifest("ctgs_cpu", dict(extra_cflags=ext.CPU_CFLAGS, extra_ldflags=ext.CPU_LDFLAGS))
    (folder / "prebuilt.json").write_text(json.dumps(manifest) + "\n")

    env = dict(os.environ, CTGS_PREBUILT="1", CTGS_CACHE_DIR=str(tmp_path / "cache"),
               PYTHONPATH=os.pathsep.join([HOOK_DIR, ROOT]))
    done = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"prebuilt {folder / 'ctgs_cpu.so'} imported" in done.stdout
    assert "ops ok 2" in done.stdout
