"""`load_scene`: a scene folder -> train/test views with cameras, images and SfM points.

Conventions (3DGS/2DGS, so numbers are comparable):
- views are sorted by image name; view idx is a test view iff idx % holdout == 0 (holdout 0/None: none), unless
  the scene folder holds TEST_LIST (test_views.txt: one image name per line), which names its test views instead:
  a protocol's split over all the photos stays the same when SfM registered only some of them;
- intrinsics are rescaled to the size of the image actually read, with separate x and y ratios
  (Tanks&Temples ships JPEGs at about half the calibration size, not exactly half on both axes);
- `Scene.extent` = 1.1 * max distance of the camera centres from their mean (3DGS `getNerfppNorm`);
- a scene whose cameras lie more than RECENTRE_EXTENTS extents from the origin (georeferenced models: UTM, ECEF)
  is moved so that their mean centre is the origin (`Scene.origin` says where, in the model's frame): float32
  positions there would be coarser than a pixel's footprint. Trained models live in this working frame;
- every camera's near plane is NEAR_FRACTION x extent (`near_plane`), so a scene behaves the same in any unit:
  an absolute near plane (gsplat 0.01, 2DGS 0.2 world units) culls a whole scene whose coordinates are small;
- RGBA images are composited over the run's background (black by default, 3DGS's), their alpha kept
  (ctgs.scene.photos); masks beside the images (masks/) or named by transforms.json leave pixels out;
- transforms.json and Blender synthetic folders (ctgs.scene.transforms) are read into the same views; without
  points they start from random points in the cameras' bounds (ctgs.scene.random_init, said in `meta`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.io.images import IMAGE_EXTENSIONS, image_info, stderr_silenced
from ctgs.render.camera import Camera
from ctgs.scene.colmap import ColmapModel, ModelImage, find_model_dir, model_file, read_colmap_model
from ctgs.scene.levels import LEVEL, level_dir
from ctgs.scene.photos import Distortion, find_mask, level_size, read_mask, read_photo
from ctgs.scene.random_init import focus_box, random_points
from ctgs.scene.transforms import Frame, check_image_sizes, read_transforms, scene_layout
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
# A scene's own list of test views (one image name per line, `#` comments), read instead of every holdout-th view.
TEST_LIST = "test_views.txt"


def is_test_index(idx: int, holdout: int | None) -> bool:
    """3DGS split rule on the name-sorted list: every `holdout`-th view, starting at 0, is a test view."""
    return bool(holdout) and idx % int(holdout) == 0


def split_views(views: list[View], holdout: int | None) -> tuple[list[View], list[View]]:
    train = [v for i, v in enumerate(views) if not is_test_index(i, holdout)]
    test = [v for i, v in enumerate(views) if is_test_index(i, holdout)]
    return train, test


def read_test_list(scene_dir: str) -> list[str] | None:
    """The image names SCENE_DIR/test_views.txt lists (None when the scene has no such file)."""
    path = os.path.join(scene_dir, TEST_LIST)
    if not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as f:
            names = [s for s in (line.split("#", 1)[0].strip() for line in f) if s]
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read the scene's test-view list ({exc}); fix or delete it (without it, "
                        "every 8th view is a test view)") from None
    if not names:
        raise UserError(f"{path}: lists no image; write one test image name per line, or delete it to take every "
                        "8th view")
    if len(set(names)) != len(names):
        twice = sorted({n for n in names if names.count(n) > 1})
        raise UserError(f"{path}: names {', '.join(twice[:3])} more than once; list each test image once")
    return names


def split_listed(views: list[View], names: list[str], path: str) -> tuple[list[View], list[View], str]:
    """(training, test, note) for a scene whose test views are `names` (its test_views.txt at `path`). A name matches
    a view's image name, or its stem where a downsampled folder changed the extension. Listed names no view has
    (photos SfM did not register) are left out and counted in the note; a list matching no view is an error."""
    listed = set(names)
    stems = {os.path.splitext(n)[0] for n in names}
    test_set = {v.name for v in views if v.name in listed or os.path.splitext(v.name)[0] in stems}
    if not test_set:
        raise UserError(f"{path}: none of its {len(names)} names is an image of this scene (first: {names[0]}); "
                        "list the scene's own image names, one per line")
    train = [v for v in views if v.name not in test_set]
    test = [v for v in views if v.name in test_set]
    note = f"{len(test)} test views from {TEST_LIST}, {len(train)} training views"
    if len(test) < len(names):
        note += f" ({len(names) - len(test)} listed names are not views of the scene and are left out)"
    return train, test, note


def _split(scene_dir: str, views: list[View], holdout: int | None, meta: dict) -> tuple[list[View], list[View]]:
    """The scene's train/test split: its test_views.txt where it has one (and a test split is asked for: holdout
    not 0), else every holdout-th view. Says which in meta["split"] / meta["test_list"]."""
    names = read_test_list(scene_dir) if holdout else None
    if names is None:
        return split_views(views, holdout)
    train, test, meta["split"] = split_listed(views, names, os.path.join(scene_dir, TEST_LIST))
    meta["test_list"] = TEST_LIST
    meta["test_names"] = [v.name for v in test]
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


def _colmap_pinhole(model: ColmapModel, image: ModelImage, path: str, width: int,
                    height: int) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a COLMAP image's camera rescaled to the image read, of size width x height."""
    intr = model.cameras[image.camera_id]
    sx, sy = width / intr.width, height / intr.height
    expected_height = intr.height * sx  # if the image kept the camera's aspect ratio
    if abs(height - expected_height) > 1.0 + MAX_ASPECT_MISMATCH * expected_height:  # 1 px: size rounding
        raise UserError(
            f"{path}: image is {width}x{height} but its camera {image.camera_id} is {intr.width}x{intr.height} "
            f"(different aspect ratio); use the image folder that belongs to this COLMAP model"
        )
    return intr.fx * sx, intr.fy * sy, intr.cx * sx, intr.cy * sy


def _camera(pinhole: tuple[float, float, float, float], width: int, height: int, viewmat: np.ndarray,
            near: float = Camera.near, origin: np.ndarray | None = None) -> Camera:
    """The Camera of a view in the working frame (`origin`: see world_origin)."""
    viewmat = np.asarray(viewmat, dtype=np.float64)
    if origin is not None and np.any(origin):
        viewmat = viewmat.copy()
        viewmat[:3, 3] += viewmat[:3, :3] @ origin  # x_model = x_work + origin
    fx, fy, cx, cy = pinhole
    return Camera(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height,
                  viewmat=torch.from_numpy(viewmat.astype(np.float32)), near=near)


@dataclass
class _Source:
    """One view to read: its image file, pose and how its camera follows from the size of the image read."""

    name: str
    path: str
    viewmat: np.ndarray  # [4, 4] float64 world -> camera, the model's frame
    pinhole: Callable[[int, int], tuple[float, float, float, float]]  # (width, height) -> fx, fy, cx, cy
    lens: Callable[[int, int], Distortion | None] = lambda width, height: None  # distortion at that size
    mask_path: str | None = None
    factor: int = 1  # shrunk this many times on reading (a level the scene has no folder for)


def _read_sources(sources: list[_Source], load_images: bool, background) -> list[tuple]:
    """(photo or None, mask or None, width, height) per source, read on a few threads."""
    def read(src: _Source):
        if load_images:
            photo = read_photo(src.path, background, src.factor, src.lens)  # undistorted at the size read
            height, width = photo.rgb.shape[:2]
        else:
            info = image_info(src.path)  # header only: the camera still needs the real size
            photo, (width, height) = None, level_size(info.width, info.height, src.factor)
        mask = read_mask(src.mask_path, width, height, src.lens(width, height)) \
            if src.mask_path and load_images else None
        return photo, mask, width, height

    with stderr_silenced(), ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        return list(pool.map(read, sources))


def _views(sources: list[_Source], loaded: list[tuple], near: float, origin: np.ndarray) -> list[View]:
    views = []
    for src, (photo, mask, width, height) in zip(sources, loaded):
        lens = src.lens(width, height)
        pinhole = lens.pinhole(width, height) if lens is not None else src.pinhole(width, height)
        views.append(View(name=src.name, camera=_camera(pinhole, width, height, src.viewmat, near, origin),
                          image_path=src.path, image=None if photo is None else photo.rgb,
                          alpha=None if photo is None else photo.alpha, mask=mask, mask_path=src.mask_path,
                          distortion=lens))
    return views


def validation_split(views: list, k: int) -> tuple[list, list]:
    """(training, validation) views for `validation_holdout = k` (tuning mode): every k-th view from the (k//2)-th
    is a validation view; k <= 0: all training, none for validation."""
    if k <= 0:
        return list(views), []
    return ([v for i, v in enumerate(views) if i % k != k // 2], [v for i, v in enumerate(views) if i % k == k // 2])


def load_scene(scene_dir: str, images: str = "images", holdout: int | None = 8, load_images: bool = True,
               background=(0.0, 0.0, 0.0)) -> Scene:
    """Read a scene folder: SCENE_DIR/sparse/0 (or sparse/) with SCENE_DIR/<images>, or a transforms.json or
    Blender synthetic folder (ctgs.scene.transforms); see the module docstring. `background`: the colour transparent
    photos are composited over (the run's)."""
    scene_dir = os.path.abspath(scene_dir)
    if not os.path.isdir(scene_dir):
        raise UserError(f"{scene_dir}: scene folder not found; run `ctgs sfm IMAGES_DIR -o {scene_dir}` or "
                        f"`ctgs demo-scene {scene_dir}`")
    if scene_layout(scene_dir) != "colmap":
        return _load_transforms(scene_dir, images, holdout, load_images, background)
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

    sources = []
    for image in model.images:
        path = _find_image(images_dir, image.name)
        if path is None:
            raise UserError(f"{os.path.join(images_dir, image.name)}: image named in the COLMAP model is missing "
                            f"on disk; restore it or use the matching image folder (--images)")
        sources.append(_Source(image.name, path, image.viewmat, partial(_colmap_pinhole, model, image, path),
                               mask_path=find_mask(scene_dir, images, image.name)))
    loaded = _read_sources(sources, load_images, background)

    centers = np.stack([-im.viewmat[:3, :3].T @ im.viewmat[:3, 3] for im in model.images])  # [C, 3]
    extent = scene_extent(centers)
    origin = world_origin(centers, extent)
    meta = {
        "layout": "colmap",
        "model_dir": model.path,
        "camera_models": sorted({c.model for c in model.cameras.values()}),
        "num_registered": len(model.images),
        "num_unregistered": model.num_unregistered,
        "holdout": holdout or 0,
        "masks": sum(s.mask_path is not None for s in sources),
    }
    train, test = _split(scene_dir, _views(sources, loaded, near_plane(extent), origin), holdout, meta)
    points, colors = _initial_points(model.points if len(model.points) else None, model.colors,
                                     [im.viewmat for im in model.images], None,
                                     f"{model_file(model.path, 'points3D')} holds none", meta)
    return Scene(root=scene_dir, train=train, test=test, points=(points - origin).astype(np.float32),
                 point_colors=colors.astype(np.float32) / 255.0, extent=extent, origin=origin, images_dir=images,
                 meta=meta)


def _initial_points(points, colors, viewmats: list, aabb, why: str, meta: dict) -> tuple[np.ndarray, np.ndarray]:
    """(points [P, 3] float64, colours [P, 3] uint8) to start from: the scene's SfM points, or without any random
    points in the cameras' bounds (instant-ngp's aabb where the file gives one), said in meta["points_note"]."""
    if points is not None:
        return np.asarray(points, dtype=np.float64), np.asarray(colors, dtype=np.uint8)
    lo, hi = aabb if aabb is not None else focus_box(viewmats)
    points, colors = random_points(lo, hi)
    where = f"instant-ngp's aabb (aabb_scale {meta['aabb_scale']:g})" if aabb is not None else \
        "the cube the cameras look at"
    meta["points"] = "random"
    meta["points_note"] = (f"no SfM points ({why}): starting from {len(points)} random points in {where}, from "
                           f"{np.round(lo, 3).tolist()} to {np.round(hi, 3).tolist()}")
    return points, colors


def _transforms_level(scene_dir: str, frame: Frame, images: str) -> tuple[str, int, str]:
    """(image file, factor still to shrink it by, image folder name for masks) of a transforms frame for `--images`:
    nerfstudio's images_N/ beside images/ when the frame's image is under images/ (made from it if missing, as for
    COLMAP scenes), else the frame's own image shrunk N times on reading."""
    folder, base = os.path.split(frame.rel)
    if images == "images":
        return frame.path, 1, folder
    m = LEVEL.match(images)
    if m is None:
        raise UserError(f"--images {images}: a transforms scene reads the images its frames name; pass images or "
                        "images_N (N times smaller)")
    if folder == "images":
        level = level_dir(scene_dir, images)
        if level is not None and os.path.isfile(os.path.join(level, base)):
            return os.path.join(level, base), 1, images
    return frame.path, int(m.group(1)), folder


def _load_transforms(scene_dir: str, images: str, holdout: int | None, load_images: bool, background) -> Scene:
    fs = read_transforms(scene_dir)
    with stderr_silenced():
        infos = {f.path: image_info(f.path) for f in fs.frames}  # headers only: the sizes the files have
    sizes = {path: (info.width, info.height) for path, info in infos.items()}
    check_image_sizes(fs.frames, sizes)
    sources = []
    for f in fs.frames:
        path, factor, folder = _transforms_level(scene_dir, f, images)
        full = sizes[f.path]
        sources.append(_Source(f.name, path, f.viewmat, partial(f.intrinsics.pinhole, full=full),
                               partial(f.intrinsics.lens, full=full),
                               f.mask_path or find_mask(scene_dir, folder, os.path.basename(f.path)), factor))
    loaded = _read_sources(sources, load_images, background)

    centers = np.stack([-f.viewmat[:3, :3].T @ f.viewmat[:3, 3] for f in fs.frames])
    extent = scene_extent(centers)
    origin = world_origin(centers, extent)
    views = _views(sources, loaded, near_plane(extent), origin)
    meta = {"layout": fs.layout, "files": fs.files, "holdout": holdout or 0, **fs.meta,
            "masks": sum(s.mask_path is not None for s in sources),
            "distorted": sum(f.intrinsics.distortion is not None for f in fs.frames)}
    if any(f.split for f in fs.frames):
        train = [v for v, f in zip(views, fs.frames) if f.split == "train"]
        test = [v for v, f in zip(views, fs.frames) if f.split == "test"]
        meta["split"] = f"the file's own: {len(train)} training, {len(test)} test views"
    else:
        train, test = _split(scene_dir, views, holdout, meta)
    if fs.ply_path:
        meta["points"] = fs.ply_path
    points, colors = _initial_points(fs.points, fs.colors, [f.viewmat for f in fs.frames], fs.aabb,
                                     f"{fs.files[0]} gives no ply_file_path", meta)
    return Scene(root=scene_dir, train=train, test=test, points=(points - origin).astype(np.float32),
                 point_colors=colors.astype(np.float32) / 255.0, extent=extent, origin=origin, images_dir=images,
                 meta=meta)
