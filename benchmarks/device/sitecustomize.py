"""Start-up hook for runs on a GPU machine without network (benchmarks/device/session.sh puts this folder on PYTHONPATH).

That machine has no network and little time, so two things are brought ready-made instead of done there:
- CTGS_PREBUILT=1: the compiled extensions (ctgs_cpu, ctgs_cuda), built on the dev machine against the same
  torch / CUDA / Python (benchmarks/device/build_extensions.py) into the ctgs cache (CTGS_CACHE_DIR), each with
  a prebuilt.json (kernel sources hash, flags, torch, Python). One that matches this machine is imported
  directly; otherwise the extension is built as usual. (torch's loader would rebuild even a matching one: its
  ninja file names the dev machine's paths.)
- CTGS_COLMAP_PICKLE=FILE: the scene's COLMAP model read on the dev machine with pycolmap (a 38 MB wheel
  that would not fit the transfer) and pickled; read_colmap_model returns it for that scene.
Neither is used by ctgs itself or by CI.
"""

import os

def prebuilt_manifest(name: str, flags: dict) -> dict:
    """What a prebuilt extension must share with this machine to be used: the kernel sources, the flags, torch
    (version and CUDA) and Python's minor version. (ctgs's own build key also hashes the compiler's name,
    which differs between the two machines' images.)"""
    import hashlib
    import sys

    import torch

    import ctgs.ops.ext as _ext

    h = _ext.hash_kernel_sources(hashlib.sha256())
    return {"name": name, "sources": h.hexdigest()[:16], "flags": repr(sorted((k, list(v)) for k, v in flags.items())),
            "torch": torch.__version__, "cuda": torch.version.cuda, "python": list(sys.version_info[:2])}


if os.environ.get("CTGS_PREBUILT") == "1":
    import importlib.util
    import json

    import ctgs.ops.ext as _ext

    _orig_jit_build = _ext.jit_build

    def _prebuilt_jit_build(name, sources, *, what, fallback, verbose, first_use, **flags):
        want = prebuilt_manifest(name, flags)
        _ext.schemas.declare()  # the ops the kernels register for, declared before the library loads (as jit_build)
        root = _ext.cache_dir() / "torch_extensions"
        for manifest in sorted(root.glob(f"{name}-*/prebuilt.json")):
            have = json.loads(manifest.read_text())
            so = manifest.parent / f"{name}.so"
            if have == want and so.is_file():
                spec = importlib.util.spec_from_file_location(name, so)
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
                print(f"ctgs (device hook): prebuilt {so} imported", flush=True)
                return module
            diff = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
            print(f"ctgs (device hook): {manifest.parent.name} differs: {diff}", flush=True)
        print(f"ctgs (device hook): no prebuilt {name} matches; building", flush=True)
        return _orig_jit_build(name, sources, what=what, fallback=fallback, verbose=verbose, first_use=first_use,
                               **flags)

    _ext.jit_build = _prebuilt_jit_build

if os.environ.get("CTGS_COLMAP_PICKLE"):
    import pickle

    import ctgs.scene.colmap as _colmap

    _orig_read = _colmap.read_colmap_model

    def _read_colmap_model(model_dir):
        with open(os.environ["CTGS_COLMAP_PICKLE"], "rb") as fh:
            model = pickle.load(fh)
        model.path = model_dir
        return model

    _colmap.read_colmap_model = _read_colmap_model
