"""The demo scene's surfaces as its demo_meta.json lists them (ctgs.scene.demo writes it: id, kind photo / flat /
smooth, center, normal, u, v, half_extents, area, world units), and which surface a point lies on."""

from __future__ import annotations

import json
import os

import numpy as np

from ctgs.scene.demo import META_NAME


def load_demo_meta(scene_dir: str) -> dict:
    """demo_meta.json of a demo scene; SystemExit with one line naming the file and the fix when it is not one."""
    path = os.path.join(scene_dir, META_NAME)
    if not os.path.isfile(path):
        raise SystemExit(f"{path}: not a demo scene (no {META_NAME}); run `ctgs demo-scene {scene_dir}`")
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except ValueError:
        meta = None
    if not isinstance(meta, dict) or "surfaces" not in meta:
        raise SystemExit(f"{path}: damaged or not a demo scene's {META_NAME}; run `ctgs demo-scene {scene_dir} "
                         "--force`")
    return meta


def surface_of(points: np.ndarray, meta: dict, tol: float = 0.02) -> np.ndarray:
    """Index into meta["surfaces"] of the surface each point [N, 3] lies on (within `tol` world units of
    its plane and inside its extents grown by `tol`), the nearest plane winning; -1 for none."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    best = np.full(len(pts), -1, dtype=np.int64)
    best_dist = np.full(len(pts), np.inf)
    for k, s in enumerate(meta["surfaces"]):
        rel = pts - np.asarray(s["center"])
        dist = np.abs(rel @ np.asarray(s["normal"]))
        inside = (np.abs(rel @ np.asarray(s["u"])) <= s["half_extents"][0] + tol) & \
                 (np.abs(rel @ np.asarray(s["v"])) <= s["half_extents"][1] + tol)
        better = inside & (dist <= tol) & (dist < best_dist)
        best = np.where(better, k, best)
        best_dist = np.where(better, dist, best_dist)
    return best
