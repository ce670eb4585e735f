"""Writing a COLMAP sparse model (binary) with known cameras and points, through pycolmap."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ctgs.scene.colmap import import_pycolmap


@dataclass(frozen=True)
class PinholeCamera:
    width: int  # pixels
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


def write_colmap_model(model_dir: str, camera: PinholeCamera | list[PinholeCamera], names: list[str],
                       viewmats: list[np.ndarray], points: np.ndarray, colors: np.ndarray) -> None:
    """One shared PINHOLE camera, or one per image (equal ones written once); images `names` with world->camera
    `viewmats` [4, 4]; points [P, 3] world units with colours [P, 3] uint8 (empty tracks: they are not
    observations)."""
    pycolmap = import_pycolmap()

    rec = pycolmap.Reconstruction()
    cams = camera if isinstance(camera, list) else [camera] * len(names)
    ids: dict[PinholeCamera, int] = {}
    for cam in cams:
        if cam not in ids:
            ids[cam] = len(ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                                                            params=[cam.fx, cam.fy, cam.cx, cam.cy],
                                                            camera_id=ids[cam]))
    for image_id, (name, viewmat, cam) in enumerate(zip(names, viewmats, cams), start=1):
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(viewmat[:3, :3], dtype=np.float64)),
                                np.asarray(viewmat[:3, 3], dtype=np.float64))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=ids[cam], image_id=image_id), pose)
    for xyz, rgb in zip(np.asarray(points, dtype=np.float64), np.asarray(colors, dtype=np.uint8)):
        rec.add_point3D(xyz, pycolmap.Track(), rgb)
    os.makedirs(model_dir, exist_ok=True)
    rec.write_binary(model_dir)
