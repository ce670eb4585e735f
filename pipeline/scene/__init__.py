"""Scenes: COLMAP models + images -> cameras, views, SfM points (see pipeline.scene.types).

`load_scene` is the entry point training and evaluation use; `pipeline.scene.demo` builds the
synthetic demo scene, `pipeline.scene.sfm` runs structure from motion, `pipeline.scene.manifests`
describes the benchmark datasets. Exports are resolved lazily: they pull in torch (Camera), which
`ctgs demo-scene`, `ctgs sfm` and `ctgs fetch` do not need.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pipeline.scene.loader import load_scene, split_views
    from pipeline.scene.types import Scene, View

_EXPORTS = {"load_scene": "pipeline.scene.loader", "split_views": "pipeline.scene.loader",
            "Scene": "pipeline.scene.types", "View": "pipeline.scene.types"}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'pipeline.scene' has no attribute {name!r}")
