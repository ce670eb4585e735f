"""Structure from motion with pycolmap: images -> undistorted PINHOLE COLMAP scene (`ctgs sfm`).

Steps: SIFT extraction -> matching (every pair, or the pairs of a retrieval / sequential pairing for large
captures) -> incremental or global mapping -> undistortion -> image pyramid (images_2/4/8) -> report. pycolmap 4.x
API. One concern a module:

- `pipeline`: `run_sfm`, the checks before any step, the steps in order, the finished scene moved into SCENE_DIR
- `steps`: each step in the work folder, and the report of the finished scene
- `markers`: the work folder's step markers and input record, from which an interrupted run resumes
- `supervise`: each long pycolmap call in a child process (`worker`), a native abort said in one line
- `progress`: photos extracted, pairs matched, photos registered, read from what a worker writes
- `options`, `report`: what can be asked (SfmOptions), what a finished scene records (SfmReport)
- `pairs`: which photo pairs a large capture matches; `worker`: the child process's pycolmap calls

The names below are resolved on first use, so that the worker (`python -m ctgs.scene.sfm.worker`) starts without
loading the pipeline.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ctgs.scene.sfm.markers import STEPS
    from ctgs.scene.sfm.options import (DEFAULT_MAX_FEATURES, EXHAUSTIVE_MAX_IMAGES, GLOBAL_MIN_IMAGES,
                                        LARGE_CAPTURE_MAX_FEATURES, LOOP_NEIGHBOURS, MAPPERS, MATCHERS, MIN_IMAGES,
                                        MIN_POINTS_PER_IMAGE, MIN_REGISTERED_FRACTION, PYRAMID_FACTORS,
                                        RETRIEVAL_NEIGHBOURS, RETRIEVAL_OVERLAP, SEQUENTIAL_OVERLAP, SfmOptions,
                                        resolve_modes)
    from ctgs.scene.sfm.pipeline import (BYTES_PER_FEATURE, BYTES_PER_PAIR, IMAGE_BYTES_FACTOR, SCENE_ENTRIES,
                                         SCENE_KIND, SFM_EXTENSIONS, StatusFn, check_free_space, check_input_images,
                                         run_sfm)
    from ctgs.scene.sfm.progress import GLOBAL_PHASES, ProgressFn
    from ctgs.scene.sfm.report import REPORT_NAME, SfmReport, read_report
    from ctgs.scene.sfm.steps import build_pyramid
    from ctgs.scene.sfm.supervise import LOW_SPACE_BYTES, SfmStopped

_MODULES = {
    "ctgs.scene.sfm.pipeline": ("run_sfm", "check_input_images", "check_free_space", "StatusFn", "SCENE_KIND",
                                "SCENE_ENTRIES", "SFM_EXTENSIONS", "BYTES_PER_FEATURE", "BYTES_PER_PAIR",
                                "IMAGE_BYTES_FACTOR"),
    "ctgs.scene.sfm.options": ("SfmOptions", "resolve_modes", "MIN_IMAGES", "MIN_REGISTERED_FRACTION",
                               "PYRAMID_FACTORS", "MATCHERS", "MAPPERS", "EXHAUSTIVE_MAX_IMAGES", "GLOBAL_MIN_IMAGES",
                               "RETRIEVAL_NEIGHBOURS", "RETRIEVAL_OVERLAP", "SEQUENTIAL_OVERLAP", "LOOP_NEIGHBOURS",
                               "MIN_POINTS_PER_IMAGE", "DEFAULT_MAX_FEATURES", "LARGE_CAPTURE_MAX_FEATURES"),
    "ctgs.scene.sfm.report": ("SfmReport", "read_report", "REPORT_NAME"),
    "ctgs.scene.sfm.markers": ("STEPS",),
    "ctgs.scene.sfm.progress": ("ProgressFn", "GLOBAL_PHASES"),
    "ctgs.scene.sfm.steps": ("build_pyramid",),
    "ctgs.scene.sfm.supervise": ("SfmStopped", "LOW_SPACE_BYTES"),
}
_EXPORTS = {name: module for module, names in _MODULES.items() for name in names}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'ctgs.scene.sfm' has no attribute {name!r}")
