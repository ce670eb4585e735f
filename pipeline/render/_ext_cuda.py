"""Just-in-time build of the CUDA backend (kernels/cuda/*.cu + kernels/bindings_cuda.cpp, module `ctgs_cuda`).

Nothing here runs at import time, and nothing is attempted without a GPU: `load_cuda()` first checks that
PyTorch sees a CUDA device and that the CUDA toolkit (nvcc) is installed, and says what to do if not. The
build (a few minutes: cub's radix sort is heavy to compile) goes next to the CPU one
(`$TORCH_EXTENSIONS_DIR/ctgs_cuda` or `<repo>/build/torch_extensions/ctgs_cuda`) and torch rebuilds when a
source or flag changes. Architectures: torch's default (the visible GPUs), or TORCH_CUDA_ARCH_LIST.
"""

from __future__ import annotations

import os
import threading
from types import ModuleType

from pipeline.errors import UserError
from pipeline.render._ext import KERNELS_DIR, _build_dir

CUDA_SOURCES = ["bindings_cuda.cpp", "cuda/preprocess.cu", "cuda/binning.cu", "cuda/forward.cu", "cuda/backward.cu"]
# The C++ standard is torch's own (it adds it): its headers need it, and the kernels are C++17-clean
# (kernels/check_cuda_build.py). -fmad=false: forward and backward each recompute alpha with the shared
# header math inside different kernels; without FMA contraction both get bit-identical values (the CPU
# backend builds with -ffp-contract=off for the same reason), so they always agree on which pairs blend.
CUDA_CFLAGS = ["-O3", "-DCTGS_WITH_CUDA"]
CUDA_NVCC_FLAGS = ["-O3", "-DCTGS_WITH_CUDA", "-fmad=false", "-lineinfo"]

_lock = threading.Lock()
_cuda_module: ModuleType | None = None


def load_cuda(verbose: bool = False) -> ModuleType:
    """The compiled CUDA backend (functions forward_cuda, backward_cuda); builds it on first call."""
    global _cuda_module
    with _lock:
        if _cuda_module is not None:
            return _cuda_module
        import torch

        if not torch.cuda.is_available():
            why = "this torch is a CPU-only build" if torch.version.cuda is None else "no CUDA device is visible"
            raise UserError(f"the cuda renderer backend needs an NVIDIA GPU ({why}): pass --backend cpu "
                            "(or reference), or install a CUDA build of torch on a machine with a GPU")
        missing = [s for s in CUDA_SOURCES if not (KERNELS_DIR / s).is_file()]
        if missing:
            raise UserError(f"{KERNELS_DIR}: kernel sources {missing} not found (needs an editable install of "
                            "the repository); pass --backend cpu")
        from torch.utils import cpp_extension

        if cpp_extension.CUDA_HOME is None:
            raise UserError("the CUDA toolkit (nvcc) was not found: install it or set CUDA_HOME to build the cuda "
                            "renderer, or pass --backend cpu")
        try:
            _cuda_module = cpp_extension.load(
                name="ctgs_cuda",
                sources=[str(KERNELS_DIR / s) for s in CUDA_SOURCES],
                extra_include_paths=[str(KERNELS_DIR / "include"), str(KERNELS_DIR)],
                extra_cflags=CUDA_CFLAGS,
                extra_cuda_cflags=CUDA_NVCC_FLAGS,
                build_directory=str(_build_dir("ctgs_cuda")),
                verbose=verbose or os.environ.get("CTGS_VERBOSE_BUILD", "") == "1",
            )
        except (RuntimeError, OSError, ImportError) as exc:
            last = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
            raise UserError(f"building the cuda renderer extension (kernels/cuda) failed: {last}; rerun with "
                            "CTGS_VERBOSE_BUILD=1 for the compiler output, or pass --backend cpu") from exc
        return _cuda_module
