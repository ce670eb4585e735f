"""Compile-only check of the CUDA backend (`make cuda-check`; CI runs it wherever nvcc is on PATH).

Compiles every kernels/cuda/*.cu with `nvcc -c -std=c++17 -O2 -I kernels/include` for sm_80 and sm_90 into
a temporary directory (nothing is linked or run: no GPU needed), and, when torch's headers are installed,
syntax-checks kernels/bindings_cuda.cpp with the host compiler (as torch's JIT build would compile it, with
-DCTGS_WITH_CUDA). Jobs run in parallel, one per core. Prints what it compiled; on failure prints the
compiler's output and exits 1. With --resources it also prints what ptxas gave every kernel for each
architecture (registers, spill stores and loads, stack frame, static shared memory): the occupancy a change
buys can be read here before any GPU runs it. It checks the kernel folder it sits in: the checkout's kernels/, or an
installed package's (`python -m ctgs._kernels.check_cuda_build`; ctgs.resources.kernels_dir() names it).
Usage: python kernels/check_cuda_build.py [--no-binding] [--jobs N] [--resources]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

KERNELS = Path(__file__).resolve().parent  # the folder checked: where this script ships with the sources
ARCHS = ("80", "90")  # A100 and H100/H200
# Same code-generation flags as the JIT build (ctgs/ops/ext_cuda.py) where they matter to validity.
NVCC_FLAGS = ["-c", "-std=c++17", "-O2", "-fmad=false", "-I", str(KERNELS / "include"), "-Werror", "all-warnings"]


def nvcc_command(nvcc: str, src: Path, out_dir: Path, resources: bool = False) -> list[str]:
    gencode = [f"-gencode=arch=compute_{a},code=sm_{a}" for a in ARCHS]
    verbose = ["-Xptxas", "-v"] if resources else []
    return [nvcc, *NVCC_FLAGS, *verbose, *gencode, str(src), "-o", str(out_dir / (src.stem + ".o"))]


_ENTRY = re.compile(r"Compiling entry function '(\w+)' for '(sm_\d+)'")
_FRAME = re.compile(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads")
_USED = re.compile(r"Used (\d+) registers(?:.*?(\d+) bytes smem)?")


def short_names(mangled: list[str]) -> dict[str, str]:
    """`backward_kernel<float, 3>` for each mangled kernel name (one c++filt call; the names as they are without it)."""
    filt = shutil.which("c++filt")
    if filt is None or not mangled:
        return {m: m for m in mangled}
    out = subprocess.run([filt, *mangled], capture_output=True, text=True).stdout.splitlines()
    names = {}
    for m, full in zip(mangled, out):
        head, _, args = full.replace("(anonymous namespace)::", "").split("(", 1)[0].partition("<")
        names[m] = head.rsplit("::", 1)[-1].split()[-1] + (f"<{args}" if args else "")
    return names


def parse_ptxas(text: str) -> list[dict]:
    """Per kernel and architecture, what `ptxas -v` printed: registers, spills, stack frame, static smem."""
    rows: list[dict] = []
    current: dict | None = None
    for line in text.splitlines():
        if m := _ENTRY.search(line):
            current = {"kernel": m.group(1), "arch": m.group(2)}
        elif current is not None and (m := _FRAME.search(line)):
            current.update(stack=int(m.group(1)), spill_stores=int(m.group(2)), spill_loads=int(m.group(3)))
        elif current is not None and (m := _USED.search(line)):
            current.update(registers=int(m.group(1)), smem=int(m.group(2) or 0))
            rows.append(current)
            current = None
    return rows


def resource_table(rows: list[dict]) -> str:
    """A markdown table of parse_ptxas rows of ctgs's own kernels (not cub's), by name."""
    rows = [r for r in rows if r["kernel"].startswith("_ZN4ctgs")]
    name = short_names(sorted({r["kernel"] for r in rows}))
    lines = ["| kernel | arch | registers | spill stores / loads (B) | stack (B) | static smem (B) |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    for r in sorted(rows, key=lambda r: (name[r["kernel"]], r["arch"])):
        lines.append(f"| `{name[r['kernel']]}` | {r['arch']} | {r['registers']} | "
                     f"{r.get('spill_stores', 0)} / {r.get('spill_loads', 0)} | {r.get('stack', 0)} | {r['smem']} |")
    return "\n".join(lines)


def cuda_include_dir() -> Path | None:
    """The toolkit's include folder (nvcc on PATH may be a wrapper script, so its own folder can mislead)."""
    nvcc = Path(shutil.which("nvcc") or "nvcc").resolve()
    candidates = [os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"), str(nvcc.parent.parent), "/usr/local/cuda"]
    for c in candidates:
        if c and (Path(c) / "include" / "cuda_runtime_api.h").is_file():
            return Path(c) / "include"
    return None


def binding_command(out_dir: Path) -> list[str] | None:
    """g++ -fsyntax-only on the binding, or None when torch's headers or a host compiler are missing.

    A CPU-only torch wheel ships the c10/cuda headers but not the generated cuda_cmake_macros.h they
    include; an empty stand-in is enough for a syntax check (it only configures DLL export macros).
    """
    try:
        from torch.utils.cpp_extension import include_paths
    except ImportError:
        return None
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        return None
    stub = out_dir / "stub" / "c10" / "cuda" / "impl"
    stub.mkdir(parents=True)
    (stub / "cuda_cmake_macros.h").write_text("#pragma once\n")
    cuda_inc = cuda_include_dir()
    if cuda_inc is None:
        return None
    incs = [*include_paths(), str(out_dir / "stub"), sysconfig.get_paths()["include"], str(cuda_inc),
            str(KERNELS / "include"), str(KERNELS)]
    # torch 2.13's headers need C++20 (its JIT build passes -std=c++20).
    return [cxx, "-fsyntax-only", "-std=c++20", "-DCTGS_WITH_CUDA", "-DTORCH_EXTENSION_NAME=ctgs_cuda",
            "-DTORCH_API_INCLUDE_EXTENSION_H", *[f"-I{p}" for p in incs], str(KERNELS / "bindings_cuda.cpp")]


def run(label: str, cmd: list[str]) -> tuple[str, int, str, float]:
    t0 = time.monotonic()
    p = subprocess.run(cmd, capture_output=True, text=True)
    return label, p.returncode, (p.stdout + p.stderr).strip(), time.monotonic() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-binding", action="store_true", help="skip the host syntax check of bindings_cuda.cpp")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel compiler processes")
    ap.add_argument("--resources", action="store_true",
                    help="also print each kernel's registers, spills, stack and shared memory (ptxas -v)")
    args = ap.parse_args()
    nvcc = shutil.which("nvcc")
    if nvcc is None:
        print("check_cuda_build: nvcc not found on PATH", file=sys.stderr)
        return 2
    sources = sorted((KERNELS / "cuda").glob("*.cu"))
    if not sources:
        print(f"check_cuda_build: no .cu files in {KERNELS / 'cuda'}", file=sys.stderr)
        return 1
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="ctgs_cuda_check_") as tmp:
        out_dir = Path(tmp)
        jobs = [(f"{s.relative_to(KERNELS.parent)} (sm_{', sm_'.join(ARCHS)})", nvcc_command(nvcc, s, out_dir, args.resources))
                for s in sources]
        if not args.no_binding:
            cmd = binding_command(out_dir)
            if cmd is None:
                print("check_cuda_build: torch headers, CUDA headers or host compiler missing: binding syntax "
                      "check skipped")
            else:
                # Longest first: the binding (torch headers) and binning.cu (cub) dominate.
                jobs.insert(0, ("kernels/bindings_cuda.cpp (host syntax, -DCTGS_WITH_CUDA)", cmd))
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            results = list(pool.map(lambda j: run(*j), jobs))
    failed = 0
    for label, rc, output, secs in results:
        print(f"check_cuda_build: {'ok    ' if rc == 0 else 'FAILED'} {label} [{secs:.1f} s]")
        if rc != 0:
            failed += 1
            print(output, file=sys.stderr)
    if args.resources and not failed:
        rows = [r for _, _, output, _ in results for r in parse_ptxas(output)]
        print(resource_table(rows))
    print(f"check_cuda_build: {len(results) - failed}/{len(results)} compiled in {time.monotonic() - t0:.1f} s "
          f"with {nvcc}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
