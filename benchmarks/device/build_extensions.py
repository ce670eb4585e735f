"""Build ctgs_cpu and ctgs_cuda on the dev machine for a GPU machine without network (benchmarks/device/session.sh).

Run with a Python and torch matching the device's (KINDS.md of the device tool: Python 3.12, torch
2.11.0+cu130), e.g. a venv made for the purpose; nvcc 13.0 compiles for sm_90 (no GPU needed). The builds
land in CTGS_CACHE_DIR/torch_extensions/<name>-<key>, each with its prebuilt.json, where ctgs finds them on the
device under CTGS_PREBUILT=1 when the manifest (sources, flags, torch, Python) matches (ctgs.ops.ext.load_prebuilt).

    CTGS_CACHE_DIR=.gpu/ctgs_cache TORCH_CUDA_ARCH_LIST=9.0 CUDA_HOME=/usr/local/cuda \
        venv312/bin/python benchmarks/device/build_extensions.py
"""

import os
import sys
import time
from pathlib import Path

import argparse  # noqa: E402

argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                        formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
os.environ.setdefault("TORCH_CUDA_ARCH_LIST", "9.0")
os.environ.setdefault("CUDA_HOME", "/usr/local/cuda")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from ctgs.ops import ext as _ext, ext_cuda as _ext_cuda  # noqa: E402

for name, sources, flags in (
        ("ctgs_cpu", _ext.CPU_SOURCES, dict(extra_cflags=_ext.CPU_CFLAGS, extra_ldflags=_ext.CPU_LDFLAGS)),
        ("ctgs_cuda", _ext_cuda.CUDA_SOURCES, dict(extra_cflags=_ext_cuda.CUDA_CFLAGS,
                                                   extra_cuda_cflags=_ext_cuda.CUDA_NVCC_FLAGS))):
    t = time.time()
    m = _ext.jit_build(name, sources, what=name, fallback="cpu", verbose=False, first_use="minutes", **flags)
    manifest = _ext.write_prebuilt_manifest(m, name, flags)
    print(f"{name}: {m.__file__} ({time.time() - t:.0f} s) {manifest.read_text().strip()}", flush=True)
