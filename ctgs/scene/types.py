"""What training and evaluation read from a scene folder."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ctgs.render.camera import Camera


@dataclass
class View:
    name: str  # image file name as stored in the COLMAP model (e.g. "000.png"), or a transforms frame's (transforms.py)
    camera: Camera  # intrinsics rescaled to the image actually read; viewmat float32 CPU
    image_path: str  # absolute path of the image file read
    image: np.ndarray | None = None  # [H, W, 3] float32 in [0, 1], loaded lazily or eagerly
    # [H, W, 1] float32 alpha of a transparent photo (composited over the run's background in `image`), else None
    alpha: np.ndarray | None = None
    mask: np.ndarray | None = None  # [H, W] bool, True where a pixel counts in the loss and the metrics; None: all
    mask_path: str | None = None  # the mask file, where the view has one
    # the OpenCV lens (ctgs.scene.photos.Distortion, at this view's size) the image was undistorted from, else None
    distortion: object = None


@dataclass
class Scene:
    root: str
    train: list[View]
    test: list[View]
    points: np.ndarray  # [P, 3] float32 SfM points, world units
    point_colors: np.ndarray  # [P, 3] float32 in [0, 1]
    extent: float  # scene extent: 1.1 * max distance of camera centres from their mean (3DGS)
    images_dir: str = "images"
    meta: dict = field(default_factory=dict)
    # [3] float64: where the scene's working frame (cameras, points, trained models) has its origin, in the COLMAP
    # model's frame; zero unless the cameras lie far from the origin (ctgs.scene.loader.world_origin).
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
