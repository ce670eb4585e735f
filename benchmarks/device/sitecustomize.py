"""Start-up hook for runs on a GPU machine without network (benchmarks/device/session.sh puts this folder on PYTHONPATH).

That machine has no network and little time, so the scene's COLMAP model is brought ready-made instead of read
there: CTGS_COLMAP_PICKLE=FILE is that model, read on the dev machine with pycolmap (a 38 MB wheel that would not
fit the transfer) and pickled; read_colmap_model returns it for that scene. (The compiled extensions travel too:
CTGS_PREBUILT=1, which ctgs.ops.ext reads itself; benchmarks/device/build_extensions.py.) Not used by ctgs itself
or by CI.
"""

import os

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
