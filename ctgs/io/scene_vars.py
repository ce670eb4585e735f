"""Make helper: `python -m ctgs.io.scene_vars SCENE` prints `DATASET IMAGES HOLDOUT` for a scene.

The Makefile's per-scene rules read the dataset, image folder and holdout from the shipped manifests
(data_manifests/, found through ctgs.resources) through this, so the facts live in one place. The manifest
layout is walked generically (any TOML/JSON file in data_manifests/; a scene entry keyed by the scene name,
or a list entry with `name = SCENE`; `images` / `holdout` looked up on the scene entry first, then on the
dataset), so it keeps working as manifests grow.
Unknown scenes print `unknown images 8` (the 3DGS defaults) with a warning on stderr.
"""

from __future__ import annotations

import json
import os
import sys
import tomllib

from ctgs.resources import manifests_dir

IMAGE_KEYS = ("images", "image_folder", "images_dir")


def _load(path: str) -> dict | None:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f) if path.endswith(".toml") else json.loads(f.read()) if path.endswith(".json") else None
    except (OSError, ValueError):
        return None


def _find_scene(node, scene: str):
    """The first dict describing `scene` inside `node` (keyed by name or with name == scene)."""
    if isinstance(node, dict):
        if node.get("name") == scene:
            return node
        if scene in node and isinstance(node[scene], dict):
            return node[scene]
        children = node.values()
    elif isinstance(node, list):
        if scene in node:
            return {}
        children = node
    else:
        return None
    for child in children:
        hit = _find_scene(child, scene)
        if hit is not None:
            return hit
    return None


def _get(entry: dict, root: dict, keys: tuple[str, ...], default):
    for d in (entry, root):
        for k in keys:
            if isinstance(d.get(k), (str, int)) and not isinstance(d.get(k), bool):
                return d[k]
    return default


def scene_vars(scene: str, manifest_dir: str | None = None) -> tuple[str, str, int]:
    manifest_dir = manifest_dir or str(manifests_dir())  # the shipped manifests (ctgs.resources)
    names = sorted(os.listdir(manifest_dir)) if os.path.isdir(manifest_dir) else []
    for name in names:
        root = _load(os.path.join(manifest_dir, name))
        if not isinstance(root, dict):
            continue
        entry = _find_scene(root, scene)
        if entry is not None:
            dataset = str(root.get("name") or root.get("dataset") or os.path.splitext(name)[0])
            return dataset, str(_get(entry, root, IMAGE_KEYS, "images")), int(_get(entry, root, ("holdout",), 8))
    print(f"scene_vars: {scene} not in {manifest_dir}; using images/ and holdout 8", file=sys.stderr)
    return "unknown", "images", 8


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m ctgs.io.scene_vars SCENE")
    print(*scene_vars(sys.argv[1]))
