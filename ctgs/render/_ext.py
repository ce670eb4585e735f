"""Just-in-time build of the C++ extension (kernels/) with torch.utils.cpp_extension.

Nothing here runs at import time: `load_cpu()` builds on first use (about a minute on 2 cores) and caches
the module. The build goes to `$TORCH_EXTENSIONS_DIR/ctgs_cpu` if set, else `<repo>/build/torch_extensions/`
(gitignored); torch rebuilds when a source or flag changes.
"""

from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path
from types import ModuleType

from ctgs.errors import UserError

# ctgs/render/_ext.py -> repo root (editable install: the kernels live next to the package).
REPO_ROOT = Path(__file__).resolve().parents[2]
KERNELS_DIR = REPO_ROOT / "kernels"
CPU_SOURCES = ["bindings.cpp", "cpu/binning.cpp", "cpu/forward.cpp", "cpu/backward.cpp", "cpu/dense.cpp"]
# -O3: the per-pixel loops are the whole cost. No -march=native: a build dir may be shared between
# machines, and forward/backward must recompute bit-identical alphas (no machine-dependent FMA contraction).
# -fno-math-errno: sqrt need not set errno, so loops calling it vectorise (results are unchanged).
CPU_CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-std=c++17"]
CPU_LDFLAGS = ["-fopenmp"]

_lock = threading.Lock()
_cpu_module: ModuleType | None = None


def _build_dir(name: str) -> Path:
    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    path = Path(root) / name if root else REPO_ROOT / "build" / "torch_extensions" / name
    path.mkdir(parents=True, exist_ok=True)
    return path


def jit_build(name: str, sources: list[str], *, what: str, fallback: str, verbose: bool, **flags) -> ModuleType:
    """Build (or reuse) extension `name` from kernels/`sources`; every failure is one UserError that says
    what to do (`fallback`: the backend to pass instead). `flags` go to torch.utils.cpp_extension.load."""
    missing = [s for s in sources if not (KERNELS_DIR / s).is_file()]
    if missing:
        raise UserError(f"{KERNELS_DIR}: kernel sources {missing} not found (needs an editable install of "
                        f"the repository); pass --backend {fallback}")
    from torch.utils import cpp_extension

    try:
        return cpp_extension.load(
            name=name,
            sources=[str(KERNELS_DIR / s) for s in sources],
            extra_include_paths=[str(KERNELS_DIR / "include"), str(KERNELS_DIR)],
            build_directory=str(_build_dir(name)),
            verbose=verbose or os.environ.get("CTGS_VERBOSE_BUILD", "") == "1",
            **flags,
        )
    except (RuntimeError, OSError, ImportError) as exc:
        last = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise UserError(f"building the {what} renderer extension (kernels/) failed: {last}; rerun with "
                        f"CTGS_VERBOSE_BUILD=1 for the compiler output, or pass --backend {fallback}") from exc


def load_cpu(verbose: bool = False) -> ModuleType:
    """The compiled CPU backend (functions forward_cpu, backward_cpu); builds it on first call."""
    global _cpu_module
    with _lock:
        if _cpu_module is not None:
            return _cpu_module
        cxx = os.environ.get("CXX", "c++")
        if shutil.which(cxx) is None:
            raise UserError(f"C++ compiler `{cxx}` not found: install g++ (apt-get install g++) to build the cpu "
                            "renderer, or pass --backend reference")
        _cpu_module = jit_build("ctgs_cpu", CPU_SOURCES, what="cpu", fallback="reference", verbose=verbose,
                                extra_cflags=CPU_CFLAGS, extra_ldflags=CPU_LDFLAGS)
        return _cpu_module


def load_cuda(verbose: bool = False) -> ModuleType:
    """The compiled CUDA backend; built by ctgs.render._ext_cuda (only where a GPU is visible)."""
    from ctgs.render._ext_cuda import load_cuda as _load_cuda

    return _load_cuda(verbose)
