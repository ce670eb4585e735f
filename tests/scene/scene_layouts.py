"""A COLMAP scene (the demo's, exact cameras) written in the transforms.json dialects, for the scene and training
tests: nerfstudio's by `ctgs convert`, instant-ngp's and the Blender synthetic layout from it, as those tools write
them (OpenGL camera axes; camera_angle_x without w and h; file paths without extension)."""

from __future__ import annotations

import json
import math
import os

import numpy as np

from ctgs.io.images import read_image, write_image
from ctgs.scene.conventions import transform_points
from ctgs.scene.convert import convert_scene
from ctgs.scene.ply_points import read_points_ply, write_points_ply


def write_nerfstudio(colmap_scene: str, out: str) -> str:
    convert_scene(colmap_scene, out, "nerfstudio")
    return out


def _ns(ns_scene: str) -> dict:
    with open(os.path.join(ns_scene, "transforms.json")) as f:
        return json.load(f)


def _source_frames(doc: dict) -> list[dict]:
    """The frames with their matrices taken back out of nerfstudio's applied_transform (the COLMAP world)."""
    undo = np.linalg.inv(np.vstack([np.array(doc["applied_transform"]), [0, 0, 0, 1]]))
    return [{**f, "transform_matrix": (undo @ np.array(f["transform_matrix"])).tolist()} for f in doc["frames"]]


def _source_points(ns_scene: str, doc: dict, out: str) -> str:
    """OUT/points.ply: the nerfstudio scene's points taken back out of its applied_transform."""
    points, colors = read_points_ply(os.path.join(ns_scene, doc["ply_file_path"]))
    undo = np.linalg.inv(np.vstack([np.array(doc["applied_transform"]), [0, 0, 0, 1]]))
    write_points_ply(os.path.join(out, "points.ply"), transform_points(undo, points), colors)
    return "points.ply"


def _angles(doc: dict) -> dict:
    return {"camera_angle_x": 2 * math.atan(0.5 * doc["w"] / doc["fl_x"]),
            "camera_angle_y": 2 * math.atan(0.5 * doc["h"] / doc["fl_y"])}


def write_instant_ngp(ns_scene: str, out: str) -> str:
    """instant-ngp's dialect beside the nerfstudio scene's images: angles, no w/h, no extensions, aabb_scale."""
    doc = _ns(ns_scene)
    frames = [{"file_path": os.path.splitext(f["file_path"])[0], "sharpness": 50.0,
               "transform_matrix": f["transform_matrix"]} for f in _source_frames(doc)]
    os.makedirs(out, exist_ok=True)
    ngp = {**_angles(doc), "aabb_scale": 4, "ply_file_path": _source_points(ns_scene, doc, out), "frames": frames}
    os.symlink(os.path.join(os.path.abspath(ns_scene), "images"), os.path.join(out, "images"))
    with open(os.path.join(out, "transforms.json"), "w") as f:
        json.dump(ngp, f, indent=1)
    return out


def write_blender(ns_scene: str, out: str, test_names: set[str], points: bool = True, alpha=None) -> str:
    """transforms_train/test.json with ./train/NAME and ./test/NAME (RGBA PNGs; `alpha`: {name: [H, W] alpha},
    else opaque), camera_angle_x only; `points`: a ply_file_path too (the published scenes have none)."""
    doc = _ns(ns_scene)
    frames = {"train": [], "test": []}
    for f in _source_frames(doc):
        name = os.path.basename(f["file_path"])
        split = "test" if name in test_names else "train"
        rgb = read_image(os.path.join(ns_scene, f["file_path"]))[:, :, :3]
        a = alpha.get(name, np.ones(rgb.shape[:2])) if alpha else np.ones(rgb.shape[:2])
        write_image(os.path.join(out, split, name), np.concatenate([rgb, a[:, :, None]], 2))
        frames[split].append({"file_path": f"./{split}/{os.path.splitext(name)[0]}", "rotation": 0.0,
                              "transform_matrix": f["transform_matrix"]})
    for split in ("train", "test"):
        blender = {"camera_angle_x": _angles(doc)["camera_angle_x"], "frames": frames[split]}
        if points:
            blender["ply_file_path"] = "points.ply"
        with open(os.path.join(out, f"transforms_{split}.json"), "w") as f:
            json.dump(blender, f, indent=1)
    if points:
        _source_points(ns_scene, doc, out)
    return out
