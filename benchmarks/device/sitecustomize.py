"""Start-up hook for runs on a lent GPU machine (benchmarks/device/session.sh puts this folder on PYTHONPATH).

That machine has no network and little time, so two things are brought ready-made instead of done there:
- CTGS_PREBUILT=1: the compiled extensions (ctgs_cpu, ctgs_cuda), built on the dev machine against the same
  torch / CUDA / Python (benchmarks/device/build_extensions.py) into the ctgs cache (CTGS_CACHE_DIR). A build
  whose key (sources, flags, torch, Python) matches is imported directly; anything else is built as usual.
  (torch's loader would rebuild it: its ninja file names the dev machine's paths.)
- CTGS_COLMAP_PICKLE=FILE: the scene's COLMAP model read on the dev machine with pycolmap (a 38 MB wheel
  that would not fit the transfer) and pickled; read_colmap_model returns it for that scene.
Neither is used by ctgs itself or by CI.
"""

import os

if os.environ.get("CTGS_PREBUILT") == "1":
    import importlib.util

    import ctgs.render._ext as _ext

    _orig_jit_build = _ext.jit_build

    def _prebuilt_jit_build(name, sources, *, what, fallback, verbose, first_use, **flags):
        key = _ext.build_key(name, flags)
        folder = _ext.build_dir(name, key)
        so = folder / f"{name}.so"
        marker = folder / _ext.BUILT_MARKER
        if so.is_file() and marker.is_file() and marker.read_text().strip() == key:
            import torch  # noqa: F401 - the extension needs torch's libraries loaded

            spec = importlib.util.spec_from_file_location(name, so)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            print(f"ctgs (device hook): prebuilt {name} {key} imported", flush=True)
            return module
        print(f"ctgs (device hook): no prebuilt {name} for key {key}; building", flush=True)
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
