"""`ctgs convert`: a scene folder written in another layout, so that a capture moves between ctgs, nerfstudio and
gsplat's examples (COLMAP).

Both layouts get OUT/images/ (the photos, copied as they are, or undistorted where the source had distortion), the
source's smaller levels (images_2/, images_4/, ... beside images/) where it has them for every photo, and masks/
where the source has masks. nerfstudio: transforms.json as `ns-process-data` writes it (OpenGL camera
axes, its `applied_transform`, the points in sparse_pc.ply, one shared camera at the top level or one per frame,
the source's own train/test split as `train_filenames` / `test_filenames`). COLMAP: sparse/0 with PINHOLE cameras;
COLMAP has no split, so a scene read from it takes every 8th view as a test view. Random initial points (a source
without points) are not written: the converted scene has none either.
"""

from __future__ import annotations

import json
import os
import shutil

import numpy as np

from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.io.images import read_image, write_image
from ctgs.scene import conventions
from ctgs.scene.colmap_write import PinholeCamera, write_colmap_model
from ctgs.scene.levels import LEVEL
from ctgs.scene.loader import load_scene
from ctgs.scene.photos import read_mask
from ctgs.scene.ply_points import write_points_ply
from ctgs.scene.transforms import TRANSFORMS

LAYOUTS = ("nerfstudio", "colmap")
POINTS_PLY = "sparse_pc.ply"  # ns-process-data's name


def _check_output(out_dir: str, force: bool) -> None:
    """UserError unless OUT is absent or empty, or (--force) an earlier converted scene: only that is replaced."""
    if not os.path.lexists(out_dir):
        return
    names = os.listdir(out_dir) if os.path.isdir(out_dir) and not os.path.islink(out_dir) else None
    if names == [] or (force and names and "images" in names and (TRANSFORMS in names or "sparse" in names)):
        return
    what = "not a converted scene" if force else "not empty"
    raise UserError(f"{out_dir}: exists and is {what}; choose another -o"
                    + ("" if force else ", or pass --force to replace an earlier converted scene"))


def _model_viewmat(camera, origin: np.ndarray) -> np.ndarray:
    """[4, 4] float64 world -> camera in the source's frame (the loader moved far-away scenes to `origin`)."""
    v = camera.viewmat.double().numpy().copy()
    v[:3, 3] -= v[:3, :3] @ origin
    return v


def _image(view, out: str, name: str) -> None:
    """OUT/images/NAME: the file as it is, or its pixels undistorted (alpha kept) where the source had a lens."""
    dst = os.path.join(out, "images", name)
    os.makedirs(os.path.dirname(dst), exist_ok=True)
    if view.distortion is None:
        shutil.copyfile(view.image_path, dst)
    else:
        write_image(dst, view.distortion.undistort(read_image(view.image_path)))


def _levels(scene_dir: str, views: list, out: str) -> list[str]:
    """The source's smaller image levels (images_N/ beside images/, the photos' names) copied to OUT where every
    view has its file there and none was undistorted; the folder names."""
    top = os.path.join(scene_dir, "images")
    if any(v.distortion is not None or os.path.dirname(v.image_path) != top for v in views):
        return []
    copied = []
    for level in sorted(d for d in os.listdir(scene_dir) if LEVEL.match(d)):
        files = [(os.path.join(scene_dir, level, os.path.basename(v.image_path)), v.name) for v in views]
        if all(os.path.isfile(src) for src, _ in files):
            os.makedirs(os.path.join(out, level))
            for src, name in files:
                shutil.copyfile(src, os.path.join(out, level, name))
            copied.append(level)
    return copied


def _mask(view, out: str, name: str) -> str | None:
    """OUT/masks/<stem>.png for a view with a mask (undistorted with its image), else None; the relative path."""
    if view.mask_path is None:
        return None
    rel = os.path.join("masks", os.path.splitext(name)[0] + ".png")
    used = read_mask(view.mask_path, view.camera.width, view.camera.height, view.distortion)
    write_image(os.path.join(out, rel), used.astype(np.float32))
    return rel


def convert_scene(scene_dir: str, out_dir: str, to: str, force: bool = False) -> dict:
    """Write SCENE_DIR (any layout ctgs reads) into OUT_DIR as `to` ("nerfstudio" or "colmap"); returns a summary
    ({"views", "points", "layout", "masks", "levels", "undistorted", "note"})."""
    if to not in LAYOUTS:
        raise UserError(f"--to {to}: unknown layout; use one of {', '.join(LAYOUTS)}")
    src, out = os.path.realpath(scene_dir), os.path.realpath(out_dir)
    if out == src or src.startswith(out + os.sep):
        raise UserError(f"{out_dir}: the output folder would replace the scene it is made from; choose another -o")
    _check_output(out_dir, force)
    scene = load_scene(scene_dir, holdout=0, load_images=False)
    views = sorted(scene.train + scene.test, key=lambda v: v.name)
    test_names = {v.name for v in scene.test}
    random_points = scene.meta.get("points") == "random"
    points = np.zeros((0, 3)) if random_points else scene.points.astype(np.float64) + scene.origin
    colors = np.zeros((0, 3), np.uint8) if random_points else \
        np.round(scene.point_colors * 255).clip(0, 255).astype(np.uint8)
    masks = 0
    with atomic.atomic_dir(out_dir) as tmp:
        os.makedirs(os.path.join(tmp, "images"))
        rows = []
        for view in views:
            _image(view, tmp, view.name)
            mask = _mask(view, tmp, view.name)
            masks += mask is not None
            rows.append((view, _model_viewmat(view.camera, scene.origin), mask))
        levels = _levels(os.path.abspath(scene_dir), views, tmp)
        if to == "nerfstudio":
            _write_nerfstudio(tmp, rows, points, colors, test_names if "split" in scene.meta else None)
        else:
            cams = [PinholeCamera(v.camera.width, v.camera.height, v.camera.fx, v.camera.fy, v.camera.cx,
                                  v.camera.cy) for v, _, _ in rows]
            write_colmap_model(os.path.join(tmp, "sparse", "0"), cams, [v.name for v, _, _ in rows],
                               [vm for _, vm, _ in rows], points, colors)
    note = None
    if random_points:
        note = "the source has no points: neither has the converted scene (training starts from random points)"
    elif to == "colmap" and "split" in scene.meta:
        note = f"COLMAP has no train/test split: the source's ({scene.meta['split']}) is not kept"
    return {"views": len(views), "points": len(points), "layout": to, "masks": masks, "levels": levels,
            "undistorted": sum(v.distortion is not None for v in views), "note": note}


def _write_nerfstudio(out: str, rows: list, points: np.ndarray, colors: np.ndarray, test_names: set | None) -> None:
    applied = np.vstack([conventions.NERFSTUDIO_APPLIED_TRANSFORM, [0.0, 0.0, 0.0, 1.0]])
    intrinsics = [{"w": v.camera.width, "h": v.camera.height, "fl_x": v.camera.fx, "fl_y": v.camera.fy,
                   "cx": v.camera.cx, "cy": v.camera.cy} for v, _, _ in rows]
    shared = all(i == intrinsics[0] for i in intrinsics)
    frames = []
    for (view, viewmat, mask), intr in zip(rows, intrinsics):
        frame = {"file_path": f"images/{view.name}",
                 "transform_matrix": (applied @ conventions.opengl_c2w_from_viewmat(viewmat)).tolist()}
        if not shared:
            frame.update(intr)
        if mask is not None:
            frame["mask_path"] = mask.replace(os.sep, "/")
        frames.append(frame)
    doc = {"camera_model": "PINHOLE", **(intrinsics[0] if shared else {}), "frames": frames,
           "applied_transform": conventions.NERFSTUDIO_APPLIED_TRANSFORM.tolist()}
    if len(points):
        write_points_ply(os.path.join(out, POINTS_PLY), conventions.transform_points(applied, points), colors)
        doc["ply_file_path"] = POINTS_PLY
    if test_names is not None:
        doc["train_filenames"] = [f["file_path"] for f, (v, _, _) in zip(frames, rows) if v.name not in test_names]
        doc["test_filenames"] = [f["file_path"] for f, (v, _, _) in zip(frames, rows) if v.name in test_names]
    atomic.write_text(os.path.join(out, TRANSFORMS), json.dumps(doc, indent=2) + "\n")
