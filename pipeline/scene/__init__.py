"""Scenes: COLMAP models + images -> cameras, views, SfM points (see pipeline.scene.types).

`load_scene` is the entry point training and evaluation use; `pipeline.scene.demo` builds the
synthetic demo scene, `pipeline.scene.sfm` runs structure from motion, `pipeline.scene.manifests`
describes the benchmark datasets.
"""

from pipeline.scene.loader import load_scene, split_views
from pipeline.scene.types import Scene, View

__all__ = ["Scene", "View", "load_scene", "split_views"]
