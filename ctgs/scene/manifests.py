"""Dataset manifests (data_manifests/<name>.toml): archives, sizes, checksums, scenes, image folder, holdout.

The manifest folder is, in order: the `manifest_dir` argument, $CTGS_MANIFEST_DIR, or the manifests
ctgs ships (ctgs.resources: the repository's data_manifests/, in an installed package ctgs/_manifests/).
A `name` ending in .toml is read as a path. `load_manifest` returns a plain dict with every scene's
`images` and `holdout` filled in from the dataset defaults.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

from ctgs.errors import UserError
from ctgs.resources import manifests_dir

MANIFEST_ENV = "CTGS_MANIFEST_DIR"
DATA_ROOT_ENV = "CTGS_DATA_ROOT"
_ARCHIVE_KEYS = {"url", "size", "sha256", "format"}
_SCENE_KEYS = {"archive", "path", "images", "holdout", "paper"}
# The paper's per-scene row (its per-scene table): what `make table` prints beside a scene's own row.
PAPER_KEYS = {"ssim": float, "psnr": float, "lpips": float, "points": int, "texels": int, "params": int, "fps": float,
              "mem_mb": float, "texels_per_primitive": float, "resolution": str}
_TOP_KEYS = {"name", "description", "holdout", "images", "archives", "scenes"}


def manifest_dir(override: str | None = None) -> Path:
    return Path(override or os.environ.get(MANIFEST_ENV) or manifests_dir())


def data_root(override: str | None = None) -> Path:
    """Where datasets are extracted: the argument, $CTGS_DATA_ROOT, or ./data."""
    return Path(override or os.environ.get(DATA_ROOT_ENV) or "data")


def available(override_dir: str | None = None) -> list[str]:
    folder = manifest_dir(override_dir)
    return sorted(p.stem for p in folder.glob("*.toml")) if folder.is_dir() else []


def _path_of(name: str, override_dir: str | None) -> Path:
    if name.endswith(".toml"):
        return Path(name)
    return manifest_dir(override_dir) / f"{name}.toml"


def load_manifest(name: str, manifest_dir_override: str | None = None) -> dict:
    """Parse and validate a dataset manifest; UserError naming the file and key on any problem."""
    path = _path_of(name, manifest_dir_override)
    if not path.is_file():
        known = ", ".join(available(manifest_dir_override)) or "none"
        raise UserError(f"{path}: no such dataset manifest; known datasets: {known}")
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: invalid TOML ({exc}); fix the manifest") from None

    def bad(what: str) -> UserError:
        return UserError(f"{path}: {what}; fix the manifest")

    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise bad(f"unknown key(s) {sorted(unknown)}")
    for key in ("archives", "scenes"):
        if not isinstance(data.get(key), dict) or not data[key]:
            raise bad(f"needs a non-empty [{key}] table")
    holdout = int(data.get("holdout", 8))
    images = str(data.get("images", "images"))
    archives = {}
    for aname, archive in data["archives"].items():
        unknown = set(archive) - _ARCHIVE_KEYS
        if unknown:
            raise bad(f"archives.{aname}: unknown key(s) {sorted(unknown)}")
        if "url" not in archive:
            raise bad(f"archives.{aname}: missing url")
        fmt = archive.get("format") or ("zip" if archive["url"].endswith(".zip") else "tar")
        if fmt not in ("zip", "tar"):
            raise bad(f"archives.{aname}: format must be zip or tar, got {fmt!r}")
        archives[aname] = {"url": archive["url"], "size": int(archive.get("size") or 0) or None,
                           "sha256": (archive.get("sha256") or "").lower() or None, "format": fmt}
    scenes = {}
    for sname, scene in data["scenes"].items():
        unknown = set(scene) - _SCENE_KEYS
        if unknown:
            raise bad(f"scenes.{sname}: unknown key(s) {sorted(unknown)}")
        if scene.get("archive") not in archives:
            raise bad(f"scenes.{sname}: archive {scene.get('archive')!r} is not in [archives]")
        paper = scene.get("paper")
        if paper is not None:
            if not isinstance(paper, dict) or set(paper) - set(PAPER_KEYS):
                raise bad(f"scenes.{sname}.paper: a table of {sorted(PAPER_KEYS)}")
            try:
                paper = {k: PAPER_KEYS[k](v) for k, v in paper.items()}
            except (TypeError, ValueError):
                raise bad(f"scenes.{sname}.paper: values must be numbers (resolution a string)") from None
        scenes[sname] = {"archive": scene["archive"], "path": str(scene.get("path", sname)).strip("/"),
                         "images": str(scene.get("images", images)), "holdout": int(scene.get("holdout", holdout)),
                         "paper": paper}
    return {"name": data.get("name", path.stem), "description": data.get("description", ""), "holdout": holdout,
            "images": images, "archives": archives, "scenes": scenes, "path": str(path)}


def scene_dir(manifest: dict, scene: str, root: str | None = None) -> Path:
    """DATA_ROOT/<dataset>/<scene>: where `ctgs fetch` puts a scene."""
    if scene not in manifest["scenes"]:
        raise UserError(f"{manifest['path']}: no scene {scene!r}; known: {', '.join(manifest['scenes'])}")
    return data_root(root) / manifest["name"] / scene
