"""The scene a run trains on, and the one a finished run was trained on, with the same views and split."""

from __future__ import annotations

from ctgs.scene.loader import load_scene, validation_split
from ctgs.scene.types import Scene


def training_scene(cfg) -> Scene:
    """The scene a training with config `cfg` (ctgs.train.config.TrainConfig: scene_dir, images, holdout, background,
    validation_holdout) loads: its photos, its test views every `holdout`-th, and with validation_holdout > 0 its
    validation views taken from the training views (the protocol's test views are then never seen)."""
    holdout = cfg.holdout if cfg.holdout > 0 else None
    scene = load_scene(cfg.scene_dir, images=cfg.images, holdout=holdout, background=cfg.background)
    if cfg.validation_holdout > 0:
        scene.train, scene.test = validation_split(scene.train, cfg.validation_holdout)
    return scene


def run_scene(run, **options) -> Scene:
    """The scene the finished run `run` (ctgs.runs.RunModel; with_scene for this machine's copy) was trained on: its
    image folder and test views. `options`: load_scene's load_images and background."""
    return load_scene(run.scene_dir, images=run.images, holdout=run.holdout, **options)
