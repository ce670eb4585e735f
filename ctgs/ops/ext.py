"""Just-in-time build of the C++ extension (the kernel sources ctgs ships) with torch.utils.cpp_extension.

Nothing here runs at import time: `load_cpu()` builds on first use (about a minute on 2 cores) and caches
the module. Building on first use rather than at `pip install`: the wheel stays pure Python (one wheel for
every platform, CPU or CUDA torch alike), the extension is compiled against the torch actually installed
(a torch upgrade later just triggers a rebuild), and `--backend reference` works without a compiler.

Build folder: `$TORCH_EXTENSIONS_DIR/<name>` when that is set (torch's own variable), else the per-user
cache `<CTGS_CACHE_DIR or ~/.cache/ctgs>/torch_extensions/<name>-<key>`, never inside the package (which
may be a read-only site-packages). The key hashes every kernel source and header, the flags, the compiler,
torch's and Python's versions, the ninja that runs the build (always the `ninja` package's when it is installed,
whatever PATH holds), and where the kernels, torch and Python's headers are: checkouts or installs with
different kernels never share (or fight over) a build, and a header change rebuilds. Neither do two checkouts or
venvs with the same kernels: torch writes absolute source and include paths into the folder's build.ninja, so one
folder shared by two of them was rebuilt (a minute) at every switch between them.

A one-line message on stderr says when a build starts; when torch recompiles a folder that was built before (it
finds the build out of date, e.g. the sources' timestamps changed in a git checkout), a line says so once the load
has taken BUILD_NOTE_S.

Prebuilt extensions, for a machine that should not spend its time building (a GPU machine used for minutes): with
CTGS_PREBUILT=1, a build folder under the cache's torch_extensions/ holding a `prebuilt.json`
(write_prebuilt_manifest: the kernel sources' hash, the flags, torch and its CUDA, Python's minor version) that
matches this machine's is imported as it is (load_prebuilt), through importlib as torch imports what it builds;
none matching, the extension is built as usual. torch's loader itself would rebuild a folder made elsewhere: its
build.ninja names the other machine's paths.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
import sysconfig
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from types import ModuleType

import torch

from ctgs.errors import UserError
from ctgs.ops import schemas
from ctgs.resources import cache_dir, kernels_dir

CPU_SOURCES = ["bindings.cpp", "cpu/binning.cpp", "cpu/forward.cpp", "cpu/backward.cpp", "cpu/dense.cpp",
               "cpu/ssim.cpp", "cpu/sh.cpp", "cpu/camera.cpp"]
# -O3: the per-pixel loops are the whole cost. No -march=native: a build dir may be shared between
# machines, and forward/backward must recompute bit-identical alphas (no machine-dependent FMA contraction).
# -fno-math-errno: sqrt need not set errno, so loops calling it vectorise (results are unchanged).
CPU_CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-std=c++17"]
CPU_LDFLAGS = ["-fopenmp"]
# Files whose content goes into the build key (sources and every header they may include).
KEYED_SUFFIXES = (".cpp", ".h", ".cu", ".cuh")
KEY_CHARS = 16  # hex digits of the sha256 kept in the folder name: 64 bits, no collisions in practice
BUILT_MARKER = ".ctgs-built"  # holds the key of the last successful build in that folder
BUILD_LOCK = ".ctgs-build-lock"  # one builder per folder (_one_builder)
TORCH_BATON = "lock"  # torch.utils.cpp_extension's FileBaton in the build folder
# Loading an up-to-date build takes about a second (torch runs ninja, which finds nothing to do); longer, and it is
# compiling: say so rather than sit silent for a minute.
BUILD_NOTE_S = 5.0
PREBUILT_ENV = "CTGS_PREBUILT"  # "1": a matching prebuilt extension is imported instead of built (load_prebuilt)
PREBUILT_MANIFEST = "prebuilt.json"

_lock = threading.Lock()
_cpu_module: ModuleType | None = None


def compiler() -> str:
    """The host C++ compiler torch's build uses: $CXX, else `c++`."""
    return os.environ.get("CXX") or "c++"


def require_compiler(what: str, fallback: str) -> None:
    """UserError naming the C++ compiler when it is not there (torch's own error is a long traceback)."""
    cxx = compiler()
    if shutil.which(cxx) is None:
        where = f"$CXX={cxx}" if os.environ.get("CXX") else f"`{cxx}` on PATH"
        raise UserError(f"C++ compiler not found ({where}): the {what} renderer is compiled on first use; install "
                        f"g++ (e.g. apt-get install g++) or set CXX to a compiler, or pass --backend {fallback}")


def ninja_binary(fallback: str) -> str:
    """The ninja every build runs: the pip package `ninja`'s (a dependency) whatever PATH holds, else PATH's. One ninja
    per environment: two ninja versions read each other's build log as out of date and rebuild everything (a venv's
    and the system's, on PATH in turn, rebuilt the extension at every switch)."""
    try:
        # not importable: PATH's, or said with the fix here rather than as torch's traceback
        import ninja

        path = os.path.join(ninja.BIN_DIR, "ninja")
        if os.access(path, os.X_OK):
            return path
    except (ImportError, AttributeError):
        pass
    found = shutil.which("ninja")
    if found is None:
        raise UserError(f"the build tool `ninja` was not found on PATH: pip install ninja, or pass --backend {fallback}")
    return found


def ninja_version(ninja: str) -> str:
    try:
        return subprocess.run([ninja, "--version"], capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


@contextmanager
def _first_on_path(folder: str) -> Iterator[None]:
    """`folder` first on PATH for the block: torch runs `ninja` from PATH."""
    before = os.environ.get("PATH")
    os.environ["PATH"] = folder + (os.pathsep + before if before else "")
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("PATH", None)
        else:
            os.environ["PATH"] = before


@contextmanager
def _one_builder(folder: Path) -> Iterator[None]:
    """One process at a time loads (and so builds) the extension in `folder`, by an fcntl lock the kernel releases
    however its holder ends. torch's own baton (a file `lock` its holder removes) stayed behind when a load was
    killed while compiling (kill -9, a cluster's time limit), and every later load waited for it forever; under this
    lock such a file is a dead load's, and goes once the build it left running (its ninja and compilers, which
    outlive it) has ended."""
    fd = os.open(folder / BUILD_LOCK, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)  # waits while another process loads here
        except OSError:
            yield  # a filesystem without locks: torch's baton alone, as before
            return
        if (folder / TORCH_BATON).exists():
            if _working_in(folder):
                print(f"ctgs: waiting for the build a stopped process left running in {folder} ...", file=sys.stderr,
                      flush=True)
                while _working_in(folder):
                    time.sleep(1.0)
            with suppress(FileNotFoundError):
                os.remove(folder / TORCH_BATON)
        yield
    finally:
        os.close(fd)


def _working_in(folder: Path) -> bool:
    """Whether a process works in `folder` (torch runs ninja there, and ninja its compilers): Linux's /proc; elsewhere
    none is seen."""
    target = os.path.realpath(folder)
    try:
        pids = [p for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return False
    for pid in pids:
        try:
            if os.readlink(f"/proc/{pid}/cwd") == target:
                return True
        except OSError:
            continue
    return False


def hash_kernel_sources(h):
    """`h` (a hashlib object) updated with every kernel source and header ctgs ships, names and contents."""
    root = kernels_dir()
    for path in sorted(p for p in root.rglob("*") if p.suffix in KEYED_SUFFIXES and p.is_file()):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h


def build_key(name: str, flags: dict, ninja: str = "") -> str:
    """Hash of everything that makes one build differ from another (see the module docstring); `ninja`: the ninja
    binary that runs it (its path and version)."""
    h = hash_kernel_sources(hashlib.sha256())
    context = [name, sorted((k, list(v)) for k, v in flags.items()), compiler(), torch.__version__,
               torch.version.cuda, sys.version_info[:2], platform.machine(), *build_paths()]
    if ninja:
        context += [os.path.realpath(ninja), ninja_version(ninja)]
    h.update(repr(context).encode())
    return h.hexdigest()[:KEY_CHARS]


def build_paths() -> list[str]:
    """The absolute paths torch writes into a build's build.ninja: the kernel sources' folder, torch's own
    (its headers and libraries) and Python's headers. Part of the build key (see the module docstring)."""

    return [str(kernels_dir().resolve()), os.path.realpath(os.path.dirname(torch.__file__)),
            os.path.realpath(sysconfig.get_paths().get("include", ""))]


def build_dir(name: str, key: str) -> Path:
    """Where extension `name` with build key `key` is built (not created here)."""
    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    if root:
        return Path(root) / name
    return cache_dir() / "torch_extensions" / f"{name}-{key}"


def prebuilt_manifest(name: str, flags: dict) -> dict:
    """What a prebuilt extension must share with this machine to be used: the kernel sources, the flags, torch
    (version and CUDA) and Python's minor version. (The build key also hashes the compiler and the install's paths,
    which differ between the machine that builds and the one that loads.)"""
    h = hash_kernel_sources(hashlib.sha256())
    return {"name": name, "sources": h.hexdigest()[:16], "flags": repr(sorted((k, list(v)) for k, v in flags.items())),
            "torch": torch.__version__, "cuda": torch.version.cuda, "python": list(sys.version_info[:2])}


def write_prebuilt_manifest(module: ModuleType, name: str, flags: dict) -> Path:
    """Mark the extension `module` (just built by jit_build with `flags`) as prebuilt: its folder's prebuilt.json."""
    path = Path(module.__file__).parent / PREBUILT_MANIFEST
    path.write_text(json.dumps(prebuilt_manifest(name, flags)) + "\n")
    return path


def load_prebuilt(name: str, flags: dict) -> ModuleType | None:
    """The prebuilt extension `name` whose prebuilt.json matches this machine (prebuilt_manifest), imported; None
    when there is none (each folder that differs is named on stderr, with what differs)."""
    want = prebuilt_manifest(name, flags)
    for manifest in sorted((cache_dir() / "torch_extensions").glob(f"{name}-*/{PREBUILT_MANIFEST}")):
        try:
            have = json.loads(manifest.read_text())
        except (OSError, ValueError) as exc:
            print(f"ctgs: {manifest}: unreadable ({exc}); not used", file=sys.stderr, flush=True)
            continue
        so = manifest.parent / f"{name}.so"
        if have == want and so.is_file():
            schemas.declare()  # the ops the kernels register for, declared before the library loads (as jit_build)
            spec = importlib.util.spec_from_file_location(name, so)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            print(f"ctgs: prebuilt {so} loaded", file=sys.stderr, flush=True)
            return module
        diff = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
        print(f"ctgs: prebuilt {manifest.parent.name} differs: {diff}", file=sys.stderr, flush=True)
    print(f"ctgs: no prebuilt {name} matches; building", file=sys.stderr, flush=True)
    return None


def jit_build(name: str, sources: list[str], *, what: str, fallback: str, verbose: bool, first_use: str,
              **flags) -> ModuleType:
    """Build (or reuse) extension `name` from the shipped kernels/`sources`; every failure is one UserError
    that says what to do (`fallback`: the backend to pass instead; `first_use`: the build time to announce).
    `flags` go to torch.utils.cpp_extension.load. With CTGS_PREBUILT=1 a matching prebuilt extension is imported
    instead (load_prebuilt)."""
    if os.environ.get(PREBUILT_ENV) == "1" and (module := load_prebuilt(name, flags)) is not None:
        return module
    kernels = kernels_dir()
    missing = [s for s in sources if not (kernels / s).is_file()]
    if missing:
        raise UserError(f"{kernels}: kernel sources {missing} not found (an incomplete install?); reinstall "
                        f"ctgs, or pass --backend {fallback}")
    ninja = ninja_binary(fallback)
    # torch's build tooling only to build: importing ctgs must not load it (tests/render/test_cpu_inputs.py)
    from torch.utils import cpp_extension

    key = build_key(name, flags, ninja)
    folder = build_dir(name, key)
    marker = folder / BUILT_MARKER
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fresh = not marker.is_file() or marker.read_text().strip() != key
    except OSError as exc:
        raise UserError(f"{folder}: cannot create the extension build folder ({exc.strerror}); set "
                        f"CTGS_CACHE_DIR to a writable folder, or pass --backend {fallback}") from exc
    note = f"ctgs: building the {what} renderer extension (first use, {first_use}) in {folder} ..."
    late = None
    if fresh:
        print(note, file=sys.stderr, flush=True)
    else:  # built before: torch may still recompile (sources touched since); say so if it takes a while
        late = threading.Timer(BUILD_NOTE_S, lambda: print(
            f"ctgs: recompiling the {what} renderer extension (torch found the build out of date, e.g. sources "
            f"touched since; {first_use}) in {folder} ...", file=sys.stderr, flush=True))
        late.daemon = True
        late.start()
    schemas.declare()  # the ops the extension's kernels register for, declared before it loads
    try:
        with _one_builder(folder), _first_on_path(os.path.dirname(ninja)):
            module = cpp_extension.load(
                name=name,
                sources=[str(kernels / s) for s in sources],
                extra_include_paths=[str(kernels / "include"), str(kernels)],
                build_directory=str(folder),
                verbose=verbose or os.environ.get("CTGS_VERBOSE_BUILD", "") == "1",
                # copies: torch appends to the lists it is given (-L paths to extra_ldflags), which would change
                # the module-level flag lists and so the build key of a later call
                **{k: list(v) for k, v in flags.items()},
            )
    except (RuntimeError, OSError, ImportError) as exc:
        if late is not None:
            late.cancel()
        last = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise UserError(f"building the {what} renderer extension ({kernels}) failed: {last}; rerun with "
                        f"CTGS_VERBOSE_BUILD=1 for the compiler output, or pass --backend {fallback}") from exc
    if late is not None:
        late.cancel()
    if fresh:
        marker.write_text(key + "\n")
    return module


def load_cpu(verbose: bool = False) -> ModuleType:
    """The compiled CPU backend (its kernels: torch.ops.ctgs.<op>, ctgs.ops.schemas); builds it on first call."""
    global _cpu_module
    with _lock:
        if _cpu_module is not None:
            return _cpu_module
        require_compiler("CPU", "reference")
        _cpu_module = jit_build("ctgs_cpu", CPU_SOURCES, what="CPU", fallback="reference", verbose=verbose,
                                first_use="~1 min", extra_cflags=CPU_CFLAGS, extra_ldflags=CPU_LDFLAGS)
        return _cpu_module
