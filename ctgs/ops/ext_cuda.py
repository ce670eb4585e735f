"""Just-in-time build of the CUDA backend (kernels/cuda/*.cu + kernels/bindings_cuda.cpp, module `ctgs_cuda`).

Nothing here runs at import time, and nothing is attempted without a GPU: `load_cuda()` first checks that
PyTorch sees a CUDA device and that the CUDA toolkit (nvcc) is installed, and says what to do if not. The
build (a few minutes: cub's radix sort is heavy to compile) goes next to the CPU one, in the per-user
cache (`$TORCH_EXTENSIONS_DIR/ctgs_cuda`, else `~/.cache/ctgs/torch_extensions/ctgs_cuda-<key>`; see
ctgs.ops.ext). Architectures: torch's default (the visible GPUs), or TORCH_CUDA_ARCH_LIST.
"""

from __future__ import annotations

import os
import threading
from types import ModuleType

import torch

from ctgs.errors import UserError
from ctgs.ops.ext import jit_build, require_compiler

CUDA_SOURCES = ["bindings_cuda.cpp", "cuda/preprocess.cu", "cuda/binning.cu", "cuda/forward.cu", "cuda/backward.cu",
                "cuda/dense.cu"]
# The C++ standard is torch's own (it adds it): its headers need it, and the kernels are C++17-clean
# (kernels/check_cuda_build.py). Forward and backward each recompute alpha with the shared header math inside
# different kernels; that math is written in arithmetic no build contracts (kernels/include/ctgs/exact.h), so both
# get bit-identical alphas and agree on which pairs blend. The rest is built without FMA contraction (-fmad=false,
# as the CPU backend's -ffp-contract=off) unless CTGS_CUDA_FMAD=1 asks for it (a build of its own, to measure).
CUDA_CFLAGS = ["-O3", "-DCTGS_WITH_CUDA"]
FMAD = "-fmad=true" if os.environ.get("CTGS_CUDA_FMAD") == "1" else "-fmad=false"
CUDA_NVCC_FLAGS = ["-O3", "-DCTGS_WITH_CUDA", FMAD, "-lineinfo"]

_lock = threading.Lock()
_cuda_module: ModuleType | None = None


def nvcc_path(cuda_home: str | None) -> str | None:
    """The nvcc torch's build will run ($CUDA_HOME/bin/nvcc), or None when it is not there."""
    if not cuda_home:
        return None
    path = os.path.join(cuda_home, "bin", "nvcc")
    return path if os.path.isfile(path) and os.access(path, os.X_OK) else None


def nvcc_where(cuda_home: str | None) -> str:
    return f"not in $CUDA_HOME/bin, CUDA_HOME={cuda_home}" if cuda_home else "not on PATH and CUDA_HOME unset"


def load_cuda(verbose: bool = False) -> ModuleType:
    """The compiled CUDA backend (its kernels: torch.ops.ctgs.<op>, ctgs.ops.schemas); builds it on first call."""
    global _cuda_module
    with _lock:
        if _cuda_module is not None:
            return _cuda_module

        if not torch.cuda.is_available():
            why = "this torch is a CPU-only build" if torch.version.cuda is None else "no CUDA device is visible"
            raise UserError(f"the cuda renderer backend needs an NVIDIA GPU ({why}): pass --backend cpu "
                            "(or reference), or install a CUDA build of torch on a machine with a GPU")
        # torch's build tooling only to build: importing ctgs must not load it (tests/render/test_cpu_inputs.py)
        from torch.utils import cpp_extension

        nvcc = nvcc_path(cpp_extension.CUDA_HOME)
        if nvcc is None:
            raise UserError(f"CUDA compiler nvcc not found ({nvcc_where(cpp_extension.CUDA_HOME)}): the cuda renderer "
                            "is compiled on first use; install the CUDA toolkit or set CUDA_HOME to it, or pass "
                            "--backend cpu")
        require_compiler("CUDA", "cpu")  # nvcc compiles host code and links with it
        _cuda_module = jit_build("ctgs_cuda", CUDA_SOURCES, what="CUDA", fallback="cpu", verbose=verbose,
                                 first_use="a few minutes", extra_cflags=CUDA_CFLAGS,
                                 extra_cuda_cflags=CUDA_NVCC_FLAGS)
        return _cuda_module


_cuda_failed = False


def cuda_fusable(*tensors) -> bool:
    """Whether the CUDA extension's per-primitive kernels (camera space, SH colour) apply to these tensors:
    all contiguous float32/float64 CUDA tensors, and the extension builds here (else callers use PyTorch,
    e.g. on a machine without the CUDA toolkit)."""
    global _cuda_failed
    if _cuda_failed or not all(t.is_cuda and t.is_contiguous() and t.dtype in (torch.float32, torch.float64)
                               for t in tensors):
        return False
    try:
        load_cuda()
    except UserError:
        _cuda_failed = True
        return False
    return True
