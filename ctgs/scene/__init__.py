"""Scenes: COLMAP models + images -> cameras, views, SfM points (see ctgs.scene.types).

`load_scene` is the entry point training and evaluation use; `ctgs.scene.demo` builds the
synthetic demo scene, `ctgs.scene.sfm` runs structure from motion, `ctgs.scene.manifests`
describes the benchmark datasets. Exports are resolved lazily: they pull in torch (Camera), which
`ctgs demo-scene`, `ctgs sfm` and `ctgs fetch` do not need.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ctgs.scene.loader import load_scene, split_views
    from ctgs.scene.types import Scene, View

_EXPORTS = {"load_scene": "ctgs.scene.loader", "split_views": "ctgs.scene.loader",
            "Scene": "ctgs.scene.types", "View": "ctgs.scene.types"}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'ctgs.scene' has no attribute {name!r}")
