"""Scenes: COLMAP models + images -> cameras, views, SfM points (see pipeline.scene.types)."""
