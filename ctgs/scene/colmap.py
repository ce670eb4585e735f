"""Reading COLMAP sparse models (binary or text) through pycolmap into plain numpy data.

Only the undistorted pinhole models are accepted for training (PINHOLE, SIMPLE_PINHOLE): the renderer
has no distortion. Everything else gets a UserError telling the user to run `ctgs sfm`, which undistorts.
"""

from __future__ import annotations

import os
import signal
import threading
from dataclasses import dataclass

import numpy as np

from ctgs.errors import UserError

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
_MODEL_FILES = ("cameras", "images", "points3D")


@dataclass(frozen=True)
class Intrinsics:
    """A COLMAP camera at its calibration size (pixels)."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


@dataclass(frozen=True)
class ModelImage:
    name: str
    camera_id: int
    viewmat: np.ndarray  # [4, 4] float64 world -> camera (COLMAP cam_from_world)


@dataclass
class ColmapModel:
    path: str  # folder holding cameras/images/points3D (.bin or .txt)
    cameras: dict[int, Intrinsics]
    images: list[ModelImage]  # registered images only, sorted by name
    num_unregistered: int
    points: np.ndarray  # [P, 3] float64 world units
    colors: np.ndarray  # [P, 3] uint8
    point_errors: np.ndarray  # [P] mean reprojection error, pixels (-1 where unknown)


def find_model_dir(scene_dir: str) -> str:
    """scene_dir/sparse/0 (COLMAP layout), or scene_dir/sparse, or scene_dir itself if it holds a model."""
    for candidate in (os.path.join(scene_dir, "sparse", "0"), os.path.join(scene_dir, "sparse"), scene_dir):
        if _has_model(candidate):
            return candidate
    raise UserError(
        f"{os.path.join(scene_dir, 'sparse', '0')}: no COLMAP model (cameras/images/points3D .bin or .txt); "
        f"run `ctgs sfm IMAGES_DIR -o {scene_dir}` first"
    )


def _has_model(folder: str) -> bool:
    return any(
        all(os.path.isfile(os.path.join(folder, f"{name}{ext}")) for name in _MODEL_FILES) for ext in (".bin", ".txt")
    )


def _model_file(model_dir: str, name: str) -> str:
    binary = os.path.join(model_dir, f"{name}.bin")
    return binary if os.path.isfile(binary) else os.path.join(model_dir, f"{name}.txt")


def import_pycolmap():
    """`import pycolmap`, keeping Python's SIGTERM handler.

    Importing pycolmap installs glog's failure-signal handler, which on SIGTERM (`kill`, `timeout`, a cluster's
    time limit) prints a native stack trace and ends the process before Python can clean up (a half-made run
    folder stays). SIGTERM gets back the handler Python had before the import (the CLI's: stop like Ctrl-C);
    the crash signals (SIGSEGV, SIGABRT, ...) keep glog's trace."""
    before = signal.getsignal(signal.SIGTERM)
    import pycolmap

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, signal.SIG_DFL if before is None else before)
    return pycolmap


def read_colmap_model(model_dir: str, *, require_pinhole: bool = True) -> ColmapModel:
    """Read a COLMAP model folder. Raises UserError on unreadable files or non-pinhole cameras."""
    pycolmap = import_pycolmap()  # heavy import, only where needed

    try:
        rec = pycolmap.Reconstruction(model_dir)
    except Exception as exc:  # pycolmap raises plain ValueError/RuntimeError on corrupt files
        detail = " ".join(str(exc).split())[:200]
        raise UserError(
            f"{model_dir}: cannot read the COLMAP model ({detail}); re-export it or run `ctgs sfm` again"
        ) from None

    cameras: dict[int, Intrinsics] = {}
    for camera_id, cam in rec.cameras.items():
        model = cam.model.name
        if model not in PINHOLE_MODELS:
            if require_pinhole:
                raise UserError(
                    f"{_model_file(model_dir, 'cameras')}: camera {camera_id} uses the {model} model, but training "
                    f"needs undistorted PINHOLE/SIMPLE_PINHOLE cameras; run `ctgs sfm` (it undistorts the images)"
                )
            continue
        p = [float(v) for v in cam.params]
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if model == "SIMPLE_PINHOLE" else (p[0], p[1], p[2], p[3])
        cameras[int(camera_id)] = Intrinsics(model, int(cam.width), int(cam.height), fx, fy, cx, cy)

    images: list[ModelImage] = []
    unregistered = 0
    for image in rec.images.values():
        if not image.has_pose:
            unregistered += 1
            continue
        viewmat = np.eye(4)
        viewmat[:3, :] = image.cam_from_world().matrix()  # [3, 4] = [R | t]
        images.append(ModelImage(image.name, int(image.camera_id), viewmat))
    images.sort(key=lambda im: im.name)

    point_ids = sorted(rec.points3D.keys())
    points = np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3)
    errors = np.array([rec.points3D[i].error for i in point_ids], dtype=np.float64).reshape(-1)
    return ColmapModel(model_dir, cameras, images, unregistered, points, colors, errors)
