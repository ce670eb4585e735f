"""The scene a run trains on, and the one a finished run was trained on, with the same views and split."""

from __future__ import annotations

from ctgs.errors import UserError
from ctgs.scene.loader import TEST_LIST, load_scene, validation_split
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
    image folder and test views. `options`: load_scene's load_images and background. UserError when the scene's
    test views are not the ones the run was trained without (its test_views.txt added, changed or removed since):
    scores on them would count training views."""
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout, **options)
    now = scene.meta.get("test_names")
    if run.holdout and (now or None) != (getattr(run, "test_views", None) or None):
        was = (f"the {len(run.test_views)} views its {TEST_LIST} listed" if getattr(run, "test_views", None)
               else f"every {run.holdout}th view")
        is_ = f"the {len(now)} its {TEST_LIST} lists" if now else f"every {run.holdout}th view (no {TEST_LIST})"
        raise UserError(f"{run.run_dir}: trained with {was} of {scene.root} held out, but the scene's test views are now "
                        f"{is_}; restore the scene's {TEST_LIST} as it was, or train again")
    return scene
