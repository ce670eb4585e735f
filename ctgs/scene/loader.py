"""`load_scene`: a COLMAP scene folder -> train/test views with cameras, images and SfM points.

Conventions (3DGS/2DGS, so numbers are comparable):
- views are sorted by image name; view idx is a test view iff idx % holdout == 0 (holdout 0/None: none);
- intrinsics are rescaled to the size of the image actually read, with separate x and y ratios
  (Tanks&Temples ships JPEGs at about half the calibration size, not exactly half on both axes);
- `Scene.extent` = 1.1 * max distance of the camera centres from their mean (3DGS `getNerfppNorm`);
- a scene whose cameras lie more than RECENTRE_EXTENTS extents from the origin (georeferenced models: UTM, ECEF)
  is moved so that their mean centre is the origin (`Scene.origin` says where, in the model's frame): float32
  positions there would be coarser than a pixel's footprint. Trained models live in this working frame;
- every camera's near plane is NEAR_FRACTION x extent (`near_plane`), so a scene behaves the same in any unit:
  an absolute near plane (gsplat 0.01, 2DGS 0.2 world units) culls a whole scene whose coordinates are small;
- RGBA images are composited over black (3DGS's default background), see ctgs.io.images.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.io.images import IMAGE_EXTENSIONS, image_info, read_rgb, stderr_silenced
from ctgs.render.camera import Camera
from ctgs.scene.colmap import ColmapModel, ModelImage, find_model_dir, model_file, read_colmap_model
from ctgs.scene.levels import level_dir
from ctgs.scene.types import Scene, View

# Image size vs calibration size: x and y ratios may differ slightly (T&T: 0.5003 vs 0.5; one pixel of
# rounding in a small image) but a larger difference means the images do not belong to this model (wrong folder, rotated or cropped images).
MAX_ASPECT_MISMATCH = 0.02
# Cameras farther than this many extents from the origin: the scene is recentred. There a float32 coordinate's step
# is 100 x 1.2e-7 = 1.2e-5 extents, about 1% of a pixel's footprint in a 1000-px view of the scene: nothing closer
# changes (the scenes measured so far: 0.03-0.8 extents), anything farther would lose detail to rounding.
RECENTRE_EXTENTS = 100.0
# The near plane as a fraction of the scene extent: 0.01 world units (Camera's default, gsplat's) at an extent of 10
# (COLMAP's normalised scale), and the same fraction at any scale.
NEAR_FRACTION = 1e-3


def is_test_index(idx: int, holdout: int | None) -> bool:
    """3DGS split rule on the name-sorted list: every `holdout`-th view, starting at 0, is a test view."""
    return bool(holdout) and idx % int(holdout) == 0


def split_views(views: list[View], holdout: int | None) -> tuple[list[View], list[View]]:
    train = [v for i, v in enumerate(views) if not is_test_index(i, holdout)]
    test = [v for i, v in enumerate(views) if is_test_index(i, holdout)]
    return train, test


def scene_extent(centers: np.ndarray) -> float:
    """1.1 * max distance of camera centres [C, 3] from their mean (world units)."""
    if len(centers) == 0:
        return 1.0
    dist = np.linalg.norm(centers - centers.mean(axis=0, keepdims=True), axis=1)
    return float(1.1 * dist.max())


def world_origin(centers: np.ndarray, extent: float) -> np.ndarray:
    """[3] float64 origin of the working frame: the mean camera centre when it lies more than RECENTRE_EXTENTS
    extents from the model's origin, else zero (the model's own frame, bit for bit)."""
    mean = np.asarray(centers, dtype=np.float64).mean(axis=0)
    if np.linalg.norm(mean) > RECENTRE_EXTENTS * max(extent, 0.0) and np.all(np.isfinite(mean)):
        return mean
    return np.zeros(3)


def check_same_frame(model_origin, scene: Scene, what: str) -> None:
    """UserError unless a model trained in the working frame `model_origin` ([3], None = zero) matches the
    scene's (a model from before recentring existed, or from another scene)."""
    a = np.zeros(3) if model_origin is None else np.asarray(model_origin, dtype=np.float64)
    if not np.allclose(a, scene.origin, rtol=0.0, atol=1e-9 * max(1.0, float(np.abs(scene.origin).max()))):
        raise UserError(f"{what}: the model's frame has its origin at {a.tolist()} but the scene {scene.root} is "
                        f"loaded with its origin at {scene.origin.tolist()}; the model was trained on another scene "
                        f"or by a ctgs that did not recentre far-away scenes: retrain it with this ctgs")


def near_plane(extent: float) -> float:
    """World-unit near plane of a scene of this extent (NEAR_FRACTION x extent; Camera's default where the extent
    is 0 or not finite, e.g. a single camera)."""
    if not (np.isfinite(extent) and extent > 0):
        return Camera.near
    return float(NEAR_FRACTION * extent)


def _find_image(images_dir: str, name: str) -> str | None:
    path = os.path.join(images_dir, name)
    if os.path.isfile(path):
        return path
    # Downsampled folders sometimes change the extension (e.g. model "a.JPG", images_4/"a.png").
    stem = os.path.splitext(path)[0]
    for ext in IMAGE_EXTENSIONS + tuple(e.upper() for e in IMAGE_EXTENSIONS):
        if os.path.isfile(stem + ext):
            return stem + ext
    return None


def _rescaled_camera(model: ColmapModel, image: ModelImage, path: str, width: int, height: int,
                     near: float = Camera.near, origin: np.ndarray | None = None) -> Camera:
    intr = model.cameras[image.camera_id]
    sx, sy = width / intr.width, height / intr.height
    expected_height = intr.height * sx  # if the image kept the camera's aspect ratio
    if abs(height - expected_height) > 1.0 + MAX_ASPECT_MISMATCH * expected_height:  # 1 px: size rounding
        raise UserError(
            f"{path}: image is {width}x{height} but its camera {image.camera_id} is {intr.width}x{intr.height} "
            f"(different aspect ratio); use the image folder that belongs to this COLMAP model"
        )
    viewmat = np.asarray(image.viewmat, dtype=np.float64)
    if origin is not None and np.any(origin):
        viewmat = viewmat.copy()
        viewmat[:3, 3] += viewmat[:3, :3] @ origin  # x_model = x_work + origin
    return Camera(
        fx=intr.fx * sx, fy=intr.fy * sy, cx=intr.cx * sx, cy=intr.cy * sy, width=width, height=height,
        viewmat=torch.from_numpy(viewmat.astype(np.float32)), near=near,
    )


def validation_split(views: list, k: int) -> tuple[list, list]:
    """(training, validation) views for `validation_holdout = k` (tuning mode): every k-th view from the (k//2)-th
    is a validation view; k <= 0: all training, none for validation."""
    if k <= 0:
        return list(views), []
    return ([v for i, v in enumerate(views) if i % k != k // 2], [v for i, v in enumerate(views) if i % k == k // 2])


def load_scene(scene_dir: str, images: str = "images", holdout: int | None = 8, load_images: bool = True) -> Scene:
    """Read SCENE_DIR/sparse/0 (or sparse/) and SCENE_DIR/<images>; see the module docstring."""
    scene_dir = os.path.abspath(scene_dir)
    if not os.path.isdir(scene_dir):
        raise UserError(f"{scene_dir}: scene folder not found; run `ctgs sfm IMAGES_DIR -o {scene_dir}` or "
                        f"`ctgs demo-scene {scene_dir}`")
    images_dir = level_dir(scene_dir, images) or os.path.join(scene_dir, images)  # images_N made if missing
    if not os.path.isdir(images_dir):
        found = sorted(d for d in os.listdir(scene_dir) if d.startswith("images") and
                       os.path.isdir(os.path.join(scene_dir, d)))
        hint = f"available: {', '.join(found)}" if found else "run `ctgs sfm` to create it"
        raise UserError(f"{images_dir}: image folder not found; {hint}")

    model = read_colmap_model(find_model_dir(scene_dir))
    if not model.images:
        raise UserError(f"{model_file(model.path, 'images')}: the COLMAP model has no registered images; run "
                        "`ctgs sfm` again")
    if len(model.points) == 0:
        raise UserError(f"{model_file(model.path, 'points3D')}: the COLMAP model has zero 3D points (training "
                        f"initialises from them); run `ctgs sfm` again or use a model with triangulated points")

    paths = []
    for image in model.images:
        path = _find_image(images_dir, image.name)
        if path is None:
            raise UserError(f"{os.path.join(images_dir, image.name)}: image named in the COLMAP model is missing "
                            f"on disk; restore it or use the matching image folder (--images)")
        paths.append(path)

    def read(i: int) -> tuple[np.ndarray | None, int, int]:
        if load_images:
            pixels = read_rgb(paths[i])
            return pixels, pixels.shape[1], pixels.shape[0]
        info = image_info(paths[i])  # header only: the camera still needs the real size
        return None, info.width, info.height

    with stderr_silenced(), ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        loaded = list(pool.map(read, range(len(paths))))

    centers = np.stack([-im.viewmat[:3, :3].T @ im.viewmat[:3, 3] for im in model.images])  # [C, 3]
    extent = scene_extent(centers)
    near = near_plane(extent)
    origin = world_origin(centers, extent)
    views = []
    for image, path, (pixels, width, height) in zip(model.images, paths, loaded):
        camera = _rescaled_camera(model, image, path, width, height, near, origin)
        views.append(View(name=image.name, camera=camera, image_path=path, image=pixels))
    train, test = split_views(views, holdout)

    return Scene(
        root=scene_dir,
        train=train,
        test=test,
        points=(np.asarray(model.points, dtype=np.float64) - origin).astype(np.float32),
        point_colors=(model.colors.astype(np.float32) / 255.0),
        extent=extent,
        origin=origin,
        images_dir=images,
        meta={
            "model_dir": model.path,
            "camera_models": sorted({c.model for c in model.cameras.values()}),
            "num_registered": len(model.images),
            "num_unregistered": model.num_unregistered,
            "holdout": holdout or 0,
        },
    )
